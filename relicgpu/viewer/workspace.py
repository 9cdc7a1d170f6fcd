"""What the viewer serves: a workspace of cases, read without ever leaving it.

A WORKSPACE is a directory of cases. A case is a directory holding
`fragments/` (mesh files) and, once assembled, `assembly/assembly.json`,
`assembly/assembly.glb` and `assembly/merged.stl`; `truth.json` from
`relicgpu synth` may sit beside them. A WORKSPACE that has a `fragments/`
folder itself is a single case.

Nothing here builds a path from a request: cases and fragments are found by
listing directories, and a request names one by its id, looked up in that
listing. Every path is resolved (symlinks followed) and kept only when it lies
inside the resolved workspace, so a symlink pointing out is never listed.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from ..io.clouds import POINT_SUFFIXES
from ..io.load import fragment_ids
from ..io.meshes import MESH_SUFFIXES

FRAGMENT_SUFFIXES = frozenset(MESH_SUFFIXES | POINT_SUFFIXES)
ASSEMBLY_FILES = ("assembly.json", "assembly.glb", "merged.stl")
# Where a case may hold the output of `relicgpu group` (groups.json), first found wins; an
# assembly.json whose fragments carry "object" (`relicgpu assemble --group`) comes before all.
GROUPS_FILES = ("assembly/groups.json", "groups/groups.json", "groups.json")


class WorkspaceError(ValueError):
    """The workspace itself is unusable (missing, not a directory)."""


class AssemblyFileError(ValueError):
    """assembly.json exists but cannot be used; the message names the file and the fault."""


@dataclass(frozen=True)
class FragmentEntry:
    name: str  # the id in the API: io.fragment_ids (the stem; the whole file name where stems collide), id#k per body
    file: str  # file name inside fragments/
    path: Path  # resolved, inside the workspace
    body: int = 0  # which of the file's fragments (io.load_fragments order) this entry is


def split_entries(entries: dict[str, FragmentEntry], body_names) -> dict[str, FragmentEntry]:
    """One entry per fragment: a file of several bodies becomes one entry per body.

    Parameters
    ----------
    entries : dict
        The file entries of a case (`Workspace.fragments`).
    body_names : callable
        entry -> the names of the fragments that file loads into (io.load_fragments order),
        or None where it cannot be read (the file's entry stays, to report the fault).
    """
    out: dict[str, FragmentEntry] = {}
    for entry in entries.values():
        names = body_names(entry) or [entry.name]
        for k, name in enumerate(names):
            out[name] = FragmentEntry(name, entry.file, entry.path, k)
    return out


@dataclass(frozen=True)
class Case:
    id: str
    path: Path  # resolved, inside the workspace

    @property
    def fragments_dir(self) -> Path:
        return self.path / "fragments"

    @property
    def assembly_dir(self) -> Path:
        return self.path / "assembly"


@dataclass(frozen=True)
class AssemblyView:
    """The parts of assembly.json the viewer uses, keyed by fragment name."""
    poses: dict  # name -> 4x4 nested list, or None when unplaced
    groups: dict  # name -> int or None (assembled piece)
    matches: list  # [{"index", "a", "b", "transform", "score", "rmse", "overlap", "used", "accepted", "reason"}]
    meta: dict = field(default_factory=dict)  # backend, engine, timings
    notes: tuple = ()
    objects: dict = field(default_factory=dict)  # name -> int or None: object group (assemble --group)


@dataclass(frozen=True)
class ObjectGroups:
    """Which object group each fragment was sorted into (relicgpu.heap.grouping), and from where."""
    groups: dict  # name -> int or None (not in the file)
    source: str  # the file, relative to the case
    method: str | None = None
    notes: tuple = ()

    @property
    def count(self) -> int:
        return len({g for g in self.groups.values() if g is not None})


class Workspace:
    def __init__(self, root) -> None:
        p = Path(root).expanduser()
        if not p.exists():
            raise WorkspaceError(f"{p}: no such directory")
        if not p.is_dir():
            raise WorkspaceError(f"{p}: not a directory")
        self.root = p.resolve()
        self.name = self.root.name or str(self.root)

    def contains(self, path: Path) -> bool:
        """True when path, with every symlink followed, lies inside the workspace."""
        try:
            return Path(path).resolve().is_relative_to(self.root)
        except (OSError, RuntimeError):  # symlink loops
            return False

    def relative(self, path) -> str:
        """A path for messages: relative to the workspace where it can be."""
        try:
            return str(Path(path).resolve().relative_to(self.root))
        except (ValueError, OSError, RuntimeError):
            return str(path)

    def is_single_case(self) -> bool:
        return _is_dir_inside(self.root / "fragments", self.root)

    def cases(self) -> dict[str, Case]:
        if self.is_single_case():
            return {self.name: Case(self.name, self.root)}
        found = {}
        for child in sorted(self.root.iterdir(), key=lambda c: c.name):
            if child.name.startswith(".") or not _is_dir_inside(child, self.root):
                continue
            if _is_dir_inside(child / "fragments", self.root):
                found[child.name] = Case(child.name, child.resolve())
        return found

    def case(self, case_id) -> Case | None:
        if not isinstance(case_id, str):
            return None
        return self.cases().get(case_id)

    def fragments(self, case: Case) -> dict[str, FragmentEntry]:
        """One entry per fragment file of a case, by id (see `split_entries` for one per body)."""
        d = case.fragments_dir
        if not _is_dir_inside(d, self.root):
            return {}
        files = []
        for p in sorted(d.iterdir(), key=lambda c: c.name):
            if p.name.startswith(".") or p.suffix.lower() not in FRAGMENT_SUFFIXES:
                continue
            try:
                real = p.resolve()
            except (OSError, RuntimeError):
                continue
            if real.is_relative_to(self.root) and real.is_file():
                files.append((p.name, real))
        entries = {}
        for (file, real), name in zip(files, fragment_ids([n for n, _ in files])):
            entries[name] = FragmentEntry(name, file, real)
        return entries

    def assembly_file(self, case: Case, name: str) -> Path | None:
        """One of the assembly outputs of a case, when it exists inside the workspace."""
        if name not in ASSEMBLY_FILES:
            return None
        p = case.assembly_dir / name
        if p.is_file() and self.contains(p):
            return p.resolve()
        return None

    def read_assembly(self, case: Case, entries: dict[str, FragmentEntry]) -> AssemblyView | None:
        p = self.assembly_file(case, "assembly.json")
        if p is None:
            return None
        label = f"{case.id}/assembly/assembly.json"
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except UnicodeDecodeError:
            raise AssemblyFileError(f"{label}: not UTF-8 text") from None
        except json.JSONDecodeError as exc:
            raise AssemblyFileError(f"{label}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
        return parse_assembly(doc, entries, label)

    def read_object_groups(self, case: Case, entries: dict[str, FragmentEntry],
                           assembly: AssemblyView | None = None) -> ObjectGroups | None:
        """The object groups of a case: from assembly.json's "object" fields, else from the first
        groups.json of GROUPS_FILES; None when there are none. A bad groups.json raises
        AssemblyFileError naming it."""
        if assembly is not None and any(g is not None for g in assembly.objects.values()):
            return ObjectGroups({n: assembly.objects.get(n) for n in entries}, "assembly/assembly.json",
                                "assemble --group")
        for rel in GROUPS_FILES:
            p = case.path / rel
            if not (p.is_file() and self.contains(p)):
                continue
            label = f"{case.id}/{rel}"
            try:
                doc = json.loads(p.resolve().read_text(encoding="utf-8"))
            except UnicodeDecodeError:
                raise AssemblyFileError(f"{label}: not UTF-8 text") from None
            except json.JSONDecodeError as exc:
                raise AssemblyFileError(f"{label}: invalid JSON at line {exc.lineno} column {exc.colno}: "
                                        f"{exc.msg}") from None
            return parse_groups(doc, entries, label, rel)
        return None


def _is_dir_inside(p: Path, root: Path) -> bool:
    try:
        return p.is_dir() and p.resolve().is_relative_to(root)
    except (OSError, RuntimeError):
        return False


def _entry_for(file_ref, entries: dict[str, FragmentEntry]) -> FragmentEntry | None:
    """Match a fragment reference of assembly.json (id, file name, stem, or a path) to a listed
    file; a body `id#k` of a file of several bodies is that file's entry."""
    if not isinstance(file_ref, str) or not file_ref:
        return None
    if file_ref in entries:
        return entries[file_ref]
    if "#" in file_ref and file_ref.rsplit("#", 1)[0] in entries:
        return entries[file_ref.rsplit("#", 1)[0]]
    base = Path(file_ref.replace("\\", "/")).name
    # a file name stands for its fragment only where the file holds one (else: which body?)
    hits = [e for e in entries.values() if e.file == base]
    if not hits:
        stem = Path(base).stem
        hits = [e for e in entries.values() if Path(e.file).stem == stem]
    return hits[0] if len(hits) == 1 else None


def _item_entry(item: dict, entries: dict[str, FragmentEntry]) -> FragmentEntry | None:
    """The entry of a fragments[] item of assembly.json or groups.json: by its name (the id,
    ``id#k`` for a body of a file of several), else by its file."""
    return _entry_for(item.get("name"), entries) or _entry_for(item.get("file"), entries)


def _matrix4(value, what: str) -> list:
    if (not isinstance(value, list) or len(value) != 4
            or not all(isinstance(r, list) and len(r) == 4 for r in value)):
        raise AssemblyFileError(f"{what} is not a 4x4 matrix (a list of 4 rows of 4 numbers)")
    out = []
    for row in value:
        for x in row:
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise AssemblyFileError(f"{what} holds {x!r}, not a finite number")
        out.append([float(x) for x in row])
    return out


def _number(value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def parse_assembly(doc, entries: dict[str, FragmentEntry], label: str = "assembly.json") -> AssemblyView:
    """Check an assembly.json document (issue 5's format) against the listed fragments."""
    if not isinstance(doc, dict):
        raise AssemblyFileError(f"{label}: the top level must be a JSON object")
    frags = doc.get("fragments")
    if not isinstance(frags, list):
        raise AssemblyFileError(f"{label}: 'fragments' must be a list")
    poses: dict = {}
    groups: dict = {}
    objects: dict = {}
    notes: list[str] = []
    for i, item in enumerate(frags):
        if not isinstance(item, dict):
            raise AssemblyFileError(f"{label}: fragments[{i}] must be an object")
        entry = _item_entry(item, entries)
        if entry is None:
            notes.append(f"{label}: fragments[{i}] names {item.get('name', item.get('file'))!r}, "
                         "which is not in fragments/")
            continue
        pose = item.get("pose")
        poses[entry.name] = None if pose is None else _matrix4(pose, f"{label}: fragments[{i}].pose")
        groups[entry.name] = _int_or_none(item.get("group"))
        objects[entry.name] = _int_or_none(item.get("object"))
    matches = []
    raw_matches = doc.get("matches", [])
    if not isinstance(raw_matches, list):
        raise AssemblyFileError(f"{label}: 'matches' must be a list")
    for i, m in enumerate(raw_matches):
        if not isinstance(m, dict):
            raise AssemblyFileError(f"{label}: matches[{i}] must be an object")
        a, b = _entry_for(m.get("a"), entries), _entry_for(m.get("b"), entries)
        if a is None or b is None:
            notes.append(f"{label}: matches[{i}] names a fragment that is not in fragments/")
            continue
        matches.append({
            "index": i,
            "a": a.name,
            "b": b.name,
            "transform": _matrix4(m.get("transform"), f"{label}: matches[{i}].transform"),
            "score": _number(m.get("score")),
            "rmse": _number(m.get("rmse")),
            "overlap": _number(m.get("overlap")),
            "used": bool(m.get("used", False)),
            "accepted": bool(m.get("accepted", True)),  # older files list only verified matches
            "reason": m.get("reason") if isinstance(m.get("reason"), str) else None,
        })
    meta = {k: doc[k] for k in ("version", "backend", "engine", "timings") if k in doc}
    return AssemblyView(poses, groups, matches, meta, tuple(notes), objects)


def _int_or_none(value):
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else None


def parse_groups(doc, entries: dict[str, FragmentEntry], label: str = "groups.json",
                 source: str = "groups.json") -> ObjectGroups:
    """Check a groups.json document (`relicgpu group`: {"fragments": [{"file", "group"}], ...})."""
    if not isinstance(doc, dict):
        raise AssemblyFileError(f"{label}: the top level must be a JSON object")
    frags = doc.get("fragments")
    if not isinstance(frags, list):
        raise AssemblyFileError(f"{label}: 'fragments' must be a list")
    groups = {n: None for n in entries}
    notes = []
    for i, item in enumerate(frags):
        if not isinstance(item, dict):
            raise AssemblyFileError(f"{label}: fragments[{i}] must be an object")
        g = _int_or_none(item.get("group"))
        if g is None:
            raise AssemblyFileError(f"{label}: fragments[{i}].group must be a whole number >= 0, "
                                    f"got {item.get('group')!r}")
        entry = _item_entry(item, entries)
        if entry is None:
            notes.append(f"{label}: fragments[{i}] names {item.get('name', item.get('file'))!r}, "
                         "which is not in fragments/")
            continue
        groups[entry.name] = g
    missing = [n for n, g in groups.items() if g is None]
    if missing:
        notes.append(f"{label}: {len(missing)} fragment(s) in no group: {', '.join(missing[:5])}"
                     + (" …" if len(missing) > 5 else ""))
    method = doc.get("method") if isinstance(doc.get("method"), str) else None
    return ObjectGroups(groups, source, method, tuple(notes))
