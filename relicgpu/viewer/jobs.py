"""Background assembly jobs of the viewer, one at a time, with a progress state
that server-sent-event streams wait on.

Progress is a snapshot, not a log: a stream sends the latest state whenever it
changes, so a job that reports every one of 100,000 pairs costs a client only
the updates it has time to read.
"""
from __future__ import annotations

import itertools
import threading
import time
import traceback
from dataclasses import dataclass, field

FINAL_STATES = ("done", "failed")


class JobBusy(RuntimeError):
    """Another job is still running."""


@dataclass
class Job:
    id: int
    case: str
    state: str = "running"  # running | done | failed
    stage: str = "starting"
    message: str = ""
    done: int | None = None
    total: int | None = None
    started: float = field(default_factory=time.time)
    finished: float | None = None
    result: dict | None = None
    error: str | None = None
    seq: int = 0

    def snapshot(self) -> dict:
        end = self.finished if self.finished is not None else time.time()
        return {
            "job": self.id,
            "case": self.case,
            "state": self.state,
            "stage": self.stage,
            "message": self.message,
            "done": self.done,
            "total": self.total,
            "elapsed_s": round(end - self.started, 3),
            "result": self.result,
            "error": self.error,
            "seq": self.seq,
        }


class JobRunner:
    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._ids = itertools.count(1)
        self._latest: Job | None = None
        self._thread: threading.Thread | None = None

    def latest(self) -> Job | None:
        return self._latest

    def get(self, job_id: int) -> Job | None:
        job = self._latest
        return job if job is not None and job.id == job_id else None

    def start(self, case: str, work) -> Job:
        """Run work(report) in a thread; work returns a JSON-able result dict.

        report(stage=None, message=None, done=None, total=None) updates the job.
        """
        with self._cond:
            if self._latest is not None and self._latest.state == "running":
                raise JobBusy(f"an assembly of case {self._latest.case!r} is still running (job {self._latest.id})")
            job = Job(next(self._ids), case)
            self._latest = job
        self._thread = threading.Thread(target=self._run, args=(job, work), name=f"relicgpu-job-{job.id}", daemon=True)
        self._thread.start()
        return job

    def _update(self, job: Job, **changes) -> None:
        with self._cond:
            for k, v in changes.items():
                setattr(job, k, v)
            job.seq += 1
            self._cond.notify_all()

    def _run(self, job: Job, work) -> None:
        def report(stage=None, message=None, done=None, total=None):
            changes = {}
            if stage is not None:
                changes["stage"] = str(stage)
            if message is not None:
                changes["message"] = str(message)
            if done is not None:
                changes["done"] = int(done)
            if total is not None:
                changes["total"] = int(total)
            if stage is not None and (done is None or total is None):
                # a new stage without counts clears the old stage's counts
                changes.setdefault("done", None)
                changes.setdefault("total", None)
            self._update(job, **changes)

        try:
            result = work(report)
        except Exception as exc:  # a failed job is reported to the page, never raised in the server
            traceback.print_exc()
            self._update(job, state="failed", stage="failed", error=f"{type(exc).__name__}: {exc}",
                         message="assembly failed", finished=time.time())
        else:
            self._update(job, state="done", stage="done", result=result, message="assembly finished",
                         finished=time.time())

    def wait(self, job: Job, seen_seq: int, timeout: float) -> bool:
        """Block until job.seq passes seen_seq (True) or timeout (False)."""
        with self._cond:
            return self._cond.wait_for(lambda: job.seq > seen_seq, timeout=timeout)

    def join(self, timeout: float | None = None) -> None:
        t = self._thread
        if t is not None:
            t.join(timeout)
