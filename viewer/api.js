// The viewer's JSON API (relicgpu/viewer/app.py), one function per endpoint.

export class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

async function request(path, options = {}) {
  const resp = await fetch(path, options);
  let body = null;
  try {
    body = await resp.json();
  } catch (_) {
    // a non-JSON body: reported below by status
  }
  if (!resp.ok) {
    throw new ApiError(resp.status, (body && body.error) || `${resp.status} ${resp.statusText} for ${path}`);
  }
  return body;
}

const enc = encodeURIComponent;

export const getCases = () => request('/api/cases');
export const getFragments = (caseId) => request(`/api/cases/${enc(caseId)}/fragments`);
export const getMatches = (caseId) => request(`/api/cases/${enc(caseId)}/matches`);
export const getContours = (caseId, name) => request(`/api/cases/${enc(caseId)}/fragments/${enc(name)}/contours`);
export const getJobs = () => request('/api/jobs');

export async function getMesh(caseId, name) {
  const m = await request(`/api/cases/${enc(caseId)}/fragments/${enc(name)}/mesh`);
  return {
    ...m,
    vertices: new Float32Array(decodeBase64(m.vertices)),
    faces: new Uint32Array(decodeBase64(m.faces)),
  };
}

function post(path, body) {
  return request(path, {
    method: 'POST',
    headers: { 'Content-Type': 'application/json' },
    body: JSON.stringify(body),
  });
}

export const postMatch = (caseId, a, b, heads) => post('/api/match', { case: caseId, a, b, heads });
export const postAssemble = (caseId) => post('/api/assemble', { case: caseId });

export function progressStream(jobId, onState) {
  // Server-sent events: one message per change of the job's state; the last one is done or failed.
  const es = new EventSource(`/api/progress?job=${enc(jobId)}`);
  es.onmessage = (ev) => {
    const state = JSON.parse(ev.data);
    if (state.state === 'done' || state.state === 'failed' || state.state === 'idle') es.close();
    onState(state);
  };
  es.onerror = () => {
    // The stream dropped: ask for the job's state, and follow it again while it still runs.
    es.close();
    getJobs().then((r) => {
      if (r.job && r.job.job === jobId && r.job.state === 'running') setTimeout(() => progressStream(jobId, onState), 2000);
      else if (r.job) onState(r.job);
    }).catch(() => onState({ state: 'failed', error: 'lost the connection to the viewer server' }));
  };
  return es;
}

function decodeBase64(text) {
  const bin = atob(text);
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return bytes.buffer;
}
