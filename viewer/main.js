// The page: case choice, fragment and match lists, view controls, picking head nodes, assembly jobs.
import * as api from './api.js';
import { FragmentScene, fragmentColor, groupColor, supportColor } from './scene.js';

const $ = (id) => document.getElementById(id);
const ui = {
  caseSelect: $('case-select'), assembleBtn: $('assemble-btn'), jobProgress: $('job-progress'), jobStatus: $('job-status'),
  toggleBtn: $('toggle-btn'), fitBtn: $('fit-btn'), blend: $('blend-slider'), explode: $('explode-slider'),
  contoursCheck: $('contours-check'), fractureCheck: $('fracture-check'), caseStatus: $('case-status'),
  fragmentList: $('fragment-list'), fragmentCount: $('fragment-count'), matchList: $('match-list'), matchCount: $('match-count'),
  pickBtn: $('pick-btn'), showAllBtn: $('show-all-btn'), pickStatus: $('pick-status'), matchResult: $('match-result'),
  overlay: $('overlay'), host: $('canvas-host'), downloads: $('downloads'),
  colourSelect: $('colour-select'), groupLegend: $('group-legend'),
};

const view = new FragmentScene(ui.host);
const state = {
  caseId: null, info: null, capabilities: {}, fragments: [], matches: [], loadToken: 0,
  assembledShown: true, picking: false, picks: [], contoursLoaded: 0, colourBy: 'fragment',
};

// For the browser test and for users poking at the console.
window.relicViewer = { view, state, fragmentColor, groupColor };

function setStatus(el, text, isError = false) {
  el.textContent = text;
  el.classList.toggle('error', isError);
}

function fmt(x, digits = 3) {
  return x === null || x === undefined ? '–' : Number(x).toPrecision(digits);
}

// --- cases -----------------------------------------------------------------------

function caseLabel(c) {
  return `${c.id} (${c.fragments}${c.assembled ? ', assembled' : ''})`;
}

async function init() {
  let cases;
  try {
    cases = await api.getCases();
  } catch (err) {
    ui.overlay.textContent = `cannot reach the viewer API: ${err.message}`;
    document.body.dataset.state = 'error';
    return;
  }
  state.capabilities = cases.capabilities || {};
  ui.caseSelect.innerHTML = '';
  for (const c of cases.cases) {
    const opt = document.createElement('option');
    opt.value = c.id;
    opt.textContent = caseLabel(c);
    ui.caseSelect.append(opt);
  }
  if (!cases.cases.length) {
    ui.overlay.textContent = `no cases in workspace ${cases.workspace}: a case is a folder holding fragments/`;
    document.body.dataset.state = 'empty';
    ui.assembleBtn.disabled = true;
    return;
  }
  const wanted = new URLSearchParams(location.hash.slice(1)).get('case');
  const first = cases.cases.find((c) => c.id === wanted) || cases.cases[0];
  ui.caseSelect.value = first.id;
  ui.assembleBtn.disabled = !state.capabilities.assemble;
  if (!state.capabilities.assemble) ui.assembleBtn.title = 'relicgpu.assemble is not installed';
  if (cases.job && cases.job.state === 'running') followJob(cases.job);
  await loadCase(first.id);
}

ui.caseSelect.addEventListener('change', () => {
  history.replaceState(null, '', `#case=${encodeURIComponent(ui.caseSelect.value)}`);
  loadCase(ui.caseSelect.value);
});

async function loadCase(caseId) {
  const token = ++state.loadToken;
  const stale = () => token !== state.loadToken;
  document.body.dataset.state = 'loading';
  delete document.body.dataset.contours;
  delete document.body.dataset.matches;
  state.caseId = caseId;
  state.picks = [];
  state.contoursLoaded = 0;
  ui.overlay.textContent = 'loading fragments…';
  ui.matchResult.textContent = '';
  ui.showAllBtn.hidden = true;
  view.clear();
  let info;
  try {
    info = await api.getFragments(caseId);
  } catch (err) {
    ui.overlay.textContent = err.message;
    document.body.dataset.state = 'error';
    return;
  }
  if (stale()) return;
  state.info = info;
  state.capabilities = info.capabilities || state.capabilities;
  state.fragments = info.fragments;
  setColourChoices(info);
  renderFragmentList();

  // Meshes, a few at a time.
  const queue = [...info.fragments];
  const failures = [];
  let loaded = 0;
  async function worker() {
    while (queue.length) {
      const f = queue.shift();
      try {
        const mesh = await api.getMesh(caseId, f.name);
        if (stale()) return;
        const rec = view.addFragment(f.name, f.index, mesh, f.pose ? f.pose.flat() : null);
        rec.group = f.group;
        loaded += 1;
        ui.overlay.textContent = `loading fragments… ${loaded}/${info.fragments.length}`;
      } catch (err) {
        failures.push(`${f.name}: ${err.message}`);
      }
    }
  }
  await Promise.all([worker(), worker(), worker(), worker()]);
  if (stale()) return;
  applyColours();

  const assembled = info.assembled && info.fragments.some((f) => f.placed);
  state.assembledShown = assembled;
  view.blend = assembled ? 1 : 0;
  view.explode = Number(ui.explode.value) / 1000;
  view.layout();
  view.fitted = false;
  view.fit();
  ui.blend.value = String(Math.round(view.blend * 1000));
  ui.blend.disabled = !assembled;
  ui.toggleBtn.disabled = !assembled;
  ui.toggleBtn.textContent = assembled ? 'Show scattered' : 'Show assembled';
  ui.explode.disabled = !assembled;

  const lines = [];
  if (!info.assembled) lines.push('not assembled yet: the fragments are shown as scanned (Assemble to place them)');
  else {
    const placed = info.fragments.filter((f) => f.placed).length;
    const groups = new Set(info.fragments.filter((f) => f.placed).map((f) => f.group)).size;
    lines.push(`${placed} of ${info.fragments.length} fragments placed, in ${groups} group${groups === 1 ? '' : 's'}`);
  }
  if (info.objects) {
    const n = info.objects.count;
    lines.push(`sorted into ${n} object group${n === 1 ? '' : 's'} (${info.objects.source}${info.objects.method ? `, ${info.objects.method}` : ''})`);
  }
  if (info.assembly_error) lines.push(info.assembly_error);
  lines.push(...(info.notes || []), ...failures);
  setStatus(ui.caseStatus, lines.join('\n'), Boolean(info.assembly_error || failures.length));
  ui.overlay.textContent = info.fragments.length ? '' : 'this case has no fragment files';
  ui.downloads.innerHTML = '';
  for (const file of info.files || []) {
    const a = document.createElement('a');
    a.href = `/api/cases/${encodeURIComponent(caseId)}/files/${encodeURIComponent(file)}`;
    a.textContent = file;
    a.title = file === 'merged.stl' ? 'the assembled solid, ready for a 3-D printer' : `download ${file}`;
    if (ui.downloads.childNodes.length) ui.downloads.append(' · ');
    ui.downloads.append(a);
  }
  document.body.dataset.state = 'ready';

  loadMatches(caseId, stale);
  if (state.capabilities.prepare) loadContours(caseId, stale);
  else setStatus(ui.pickStatus, 'relicgpu.prepare is not installed: no contours, no matching by hand');
  ui.pickBtn.disabled = !(state.capabilities.prepare && state.capabilities.match);
}

async function loadContours(caseId, stale) {
  const names = state.fragments.map((f) => f.name);
  for (const name of names) {
    if (stale()) return;
    setStatus(ui.pickStatus, `segmenting fragments and tracing contours… ${state.contoursLoaded}/${names.length}`);
    try {
      const data = await api.getContours(caseId, name);
      if (stale()) return;
      view.setContours(name, data);
      state.contoursLoaded += 1;
      markContourCount(name, data);
    } catch (err) {
      if (stale()) return;
      setStatus(ui.pickStatus, `contours of ${name}: ${err.message}`, true);
      document.body.dataset.contours = 'error';
      return;
    }
  }
  setStatus(ui.pickStatus, `contours of ${names.length} fragments ready`);
  document.body.dataset.contours = 'ready';
}

// --- colours: by fragment, by object group, by assembled piece, by how a piece is held ----

const SUPPORT_ORDER = ['loop', 'chain', 'one', 'unplaced'];
const SUPPORT_LABELS = {
  loop: 'on a closed loop of matches',
  chain: 'in a chain of matches, no loop',
  one: 'rests on one match alone',
  unplaced: 'unplaced',
};

function supportOf(f) {
  if (!f.placed) return 'unplaced';
  if (f.on_loop) return 'loop';
  return f.used_matches > 1 ? 'chain' : 'one';
}

function colourOf(f) {
  if (state.colourBy === 'object') return groupColor(f.object);
  if (state.colourBy === 'assembly') return groupColor(f.placed ? f.group : null);
  if (state.colourBy === 'support') return supportColor(supportOf(f));
  return fragmentColor(f.index);
}

function setColourChoices(info) {
  const assembled = Boolean(info.assembled);
  const options = { fragment: true, object: Boolean(info.objects), assembly: assembled, support: assembled };
  for (const opt of ui.colourSelect.options) opt.disabled = !options[opt.value];
  // A heap sorted into objects is shown by object; otherwise keep the choice while it stays possible.
  if (info.objects) state.colourBy = 'object';
  else if (!options[state.colourBy]) state.colourBy = 'fragment';
  ui.colourSelect.value = state.colourBy;
  document.body.dataset.colour = state.colourBy;
}

function applyColours() {
  for (const f of state.fragments) {
    view.setColor(f.name, colourOf(f).color);
    const sw = ui.fragmentList.querySelector(`li[data-name="${CSS.escape(f.name)}"] .swatch`);
    if (sw) sw.style.background = `#${colourOf(f).color.getHexString()}`;
  }
  renderGroupLegend();
  document.body.dataset.colour = state.colourBy;
}

function renderGroupLegend() {
  ui.groupLegend.innerHTML = '';
  if (state.colourBy === 'fragment') return;
  const support = state.colourBy === 'support';
  const key = state.colourBy === 'object' ? (f) => f.object
    : support ? supportOf : (f) => (f.placed ? f.group : null);
  const members = new Map();
  for (const f of state.fragments) {
    const k = key(f) ?? null;
    if (!members.has(k)) members.set(k, []);
    members.get(k).push(f.name);
  }
  const keys = [...members.keys()].sort(support
    ? (a, b) => SUPPORT_ORDER.indexOf(a) - SUPPORT_ORDER.indexOf(b)
    : (a, b) => (a === null) - (b === null) || a - b);
  for (const k of keys) {
    const span = document.createElement('span');
    span.dataset.group = k === null ? '' : String(k);
    const sw = document.createElement('i');
    sw.className = 'swatch';
    sw.style.background = `#${(support ? supportColor(k) : groupColor(k)).color.getHexString()}`;
    const word = state.colourBy === 'object' ? 'object' : 'piece';
    const label = support ? SUPPORT_LABELS[k]
      : k === null ? (state.colourBy === 'object' ? 'no object' : 'unplaced') : `${word} ${k}`;
    span.append(sw, `${label} (${members.get(k).length})`);
    span.title = `${members.get(k).join(', ')}: click to frame them`;
    span.addEventListener('click', () => view.fit(members.get(k)));
    ui.groupLegend.append(span);
  }
}

ui.colourSelect.addEventListener('change', () => {
  state.colourBy = ui.colourSelect.value;
  applyColours();
});

// --- lists -----------------------------------------------------------------------

function renderFragmentList() {
  ui.fragmentList.innerHTML = '';
  ui.fragmentCount.textContent = `(${state.fragments.length})`;
  for (const f of state.fragments) {
    const li = document.createElement('li');
    li.dataset.name = f.name;
    const sw = document.createElement('span');
    sw.className = 'swatch';
    sw.style.background = `#${colourOf(f).color.getHexString()}`;
    const cb = document.createElement('input');
    cb.type = 'checkbox';
    cb.checked = true;
    cb.title = 'show or hide';
    cb.addEventListener('click', (ev) => ev.stopPropagation());
    cb.addEventListener('change', () => view.setVisible(f.name, cb.checked));
    const name = document.createElement('span');
    name.className = 'name';
    name.textContent = f.name;
    name.title = f.file;
    const tag = document.createElement('span');
    tag.className = 'tag';
    const tags = [];
    if (state.info.objects) tags.push(f.object === null || f.object === undefined ? 'no object' : `object ${f.object}`);
    if (state.info.assembled) tags.push(f.placed ? `group ${f.group ?? '?'}` : 'unplaced');
    if (state.info.assembled && f.placed && supportOf(f) !== 'loop') tags.push(f.used_matches > 1 ? 'no loop' : 'one match');
    tag.textContent = tags.join(' · ');
    li.append(cb, sw, name, tag);
    li.addEventListener('click', () => focusFragment(f.name));
    ui.fragmentList.append(li);
  }
}

function markContourCount(name, data) {
  const li = ui.fragmentList.querySelector(`li[data-name="${CSS.escape(name)}"] .name`);
  if (li) li.title = `${li.title} · ${data.contours.length} contours, ${data.region_is_fracture.filter(Boolean).length} fracture regions`;
}

function focusFragment(name) {
  if (view.pair && name !== view.pair.a && name !== view.pair.b) leavePairView();
  for (const li of ui.fragmentList.children) li.classList.toggle('active', li.dataset.name === name);
  const rec = view.fragments.get(name);
  if (!rec) return;
  if (!rec.mesh.visible && !view.pair) {
    view.setVisible(name, true);
    const cb = ui.fragmentList.querySelector(`li[data-name="${CSS.escape(name)}"] input`);
    if (cb) cb.checked = true;
  }
  view.fit([name]);
  view.flash(name);
}

// body[data-matches] is 'ready' once the match list of the case shown is filled (or known empty)
async function loadMatches(caseId, stale) {
  ui.matchList.innerHTML = '';
  ui.matchCount.textContent = '';
  document.body.dataset.matches = 'loading';
  if (!state.info.assembled) {
    document.body.dataset.matches = 'ready';
    return;
  }
  let data;
  try {
    data = await api.getMatches(caseId);
  } catch (err) {
    setStatus(ui.caseStatus, `${ui.caseStatus.textContent}\nmatches: ${err.message}`, true);
    document.body.dataset.matches = 'error';
    return;
  }
  if (stale()) return;
  state.matches = data.matches;
  ui.matchCount.textContent = `(${data.matches.length})`;
  const sorted = [...data.matches].sort((x, y) => (y.used - x.used) || ((y.score ?? -Infinity) - (x.score ?? -Infinity)));
  for (const m of sorted) {
    const li = document.createElement('li');
    li.classList.toggle('unused', !m.used);
    li.dataset.index = m.index;
    const name = document.createElement('span');
    name.className = 'name';
    name.textContent = `${m.a} ↔ ${m.b}`;
    const score = document.createElement('span');
    score.className = 'score';
    const verdict = m.used ? '' : (m.accepted === false ? ' (rejected)' : ' (unused)');
    score.textContent = `${fmt(m.score)}${verdict}`;
    li.title = `score ${fmt(m.score)}, rmse ${fmt(m.rmse)}, overlap ${fmt(m.overlap)}`
      + `${m.reason ? `; ${m.reason}` : ''}; click to show the pair alone`;
    li.append(name, score);
    li.addEventListener('click', () => {
      for (const x of ui.matchList.children) x.classList.toggle('active', x === li);
      view.clearMarkers();
      state.picks = [];
      setStatus(ui.pickStatus, '');
      showPair(m.a, m.b, m.transform);
      ui.matchResult.innerHTML = '';
      const reason = m.reason || (m.used ? 'used in the assembly' : 'not used in the assembly');
      ui.matchResult.append(describeMatch({ ...m, accepted: m.used, reason }));
    });
    ui.matchList.append(li);
  }
  document.body.dataset.matches = 'ready';
}

function showPair(a, b, transform) {
  view.showPair(a, b, transform);
  view.fit([a, b]);
  ui.showAllBtn.hidden = false;
}

function leavePairView() {
  view.clearPair();
  view.clearMarkers();
  state.picks = [];
  for (const x of ui.matchList.children) x.classList.remove('active');
  ui.showAllBtn.hidden = true;
  view.fit();
}

ui.showAllBtn.addEventListener('click', leavePairView);

function describeMatch(m) {
  const box = document.createElement('div');
  const verdict = document.createElement('div');
  verdict.className = `verdict ${m.accepted ? 'ok' : 'no'}`;
  verdict.textContent = `${m.a} ↔ ${m.b}: ${m.accepted ? 'accepted' : 'rejected'}`;
  const rest = document.createElement('div');
  const lines = [`score ${fmt(m.score)}   rmse ${fmt(m.rmse)}   overlap ${fmt(m.overlap)}`];
  if (m.correspondences) lines.push(`${m.correspondences.length} contour correspondences (contours ${m.contour_a} and ${m.contour_b})`);
  if (m.reason) lines.push(m.reason);
  rest.textContent = lines.join('\n');
  box.append(verdict, rest);
  return box;
}

// --- view controls -----------------------------------------------------------------

function followFrame() {
  // The camera follows the fragments as they move, keeping the user's viewing direction.
  ui.blend.value = String(Math.round(view.blend * 1000));
  view.fit();
}

ui.toggleBtn.addEventListener('click', () => {
  state.assembledShown = !state.assembledShown;
  ui.toggleBtn.textContent = state.assembledShown ? 'Show scattered' : 'Show assembled';
  document.body.dataset.anim = 'running';
  view.onAnimationEnd = () => {
    view.fit();
    document.body.dataset.anim = 'idle';
  };
  view.animateBlend(state.assembledShown ? 1 : 0, 900, followFrame);
});

ui.blend.addEventListener('input', () => {
  view.setBlend(Number(ui.blend.value) / 1000);
  state.assembledShown = view.blend > 0.5;
  ui.toggleBtn.textContent = state.assembledShown ? 'Show scattered' : 'Show assembled';
});

ui.explode.addEventListener('input', () => view.setExplode(Number(ui.explode.value) / 1000));
ui.explode.addEventListener('change', () => view.fit());
ui.fitBtn.addEventListener('click', () => view.fit());
ui.contoursCheck.addEventListener('change', () => view.setShowContours(ui.contoursCheck.checked));
ui.fractureCheck.addEventListener('change', () => view.setShowFracture(ui.fractureCheck.checked));

// --- picking head nodes (the paper's interactive step) -----------------------------

ui.pickBtn.addEventListener('click', () => {
  state.picking = !state.picking;
  ui.pickBtn.setAttribute('aria-pressed', String(state.picking));
  ui.host.classList.toggle('picking', state.picking);
  state.picks = [];
  view.clearMarkers();
  setStatus(ui.pickStatus, state.picking ? 'click a contour point on the first fragment' : '');
});

let downAt = null;
ui.host.addEventListener('pointerdown', (ev) => { downAt = [ev.clientX, ev.clientY]; });
ui.host.addEventListener('pointerup', (ev) => {
  if (!state.picking || !downAt) return;
  const moved = Math.hypot(ev.clientX - downAt[0], ev.clientY - downAt[1]);
  downAt = null;
  if (moved > 5) return; // that was an orbit, not a click
  const hit = view.pickContourPoint(ev.clientX, ev.clientY);
  if (!hit) {
    setStatus(ui.pickStatus, 'no contour point there: click on (or next to) a yellow contour line');
    return;
  }
  if (state.picks.length === 1 && state.picks[0].name === hit.name) {
    setStatus(ui.pickStatus, `that is ${hit.name} again: pick a point on another fragment`);
    return;
  }
  if (state.picks.length >= 2) {
    state.picks = [];
    view.clearMarkers();
  }
  state.picks.push(hit);
  view.addMarker(hit.name, hit.contour, hit.point);
  if (state.picks.length === 1) {
    setStatus(ui.pickStatus, `head of ${hit.name}: contour ${hit.contour}, point ${hit.point}; now a point on another fragment`);
  } else {
    runHandMatch(state.picks[0], state.picks[1]);
  }
});

async function runHandMatch(pa, pb) {
  const heads = [pa.contour, pa.point, pb.contour, pb.point];
  setStatus(ui.pickStatus, `matching ${pa.name} and ${pb.name} from heads [${heads.join(', ')}]…`);
  ui.matchResult.textContent = '';
  document.body.dataset.match = 'running';
  const caseId = state.caseId;
  try {
    const m = await api.postMatch(caseId, pa.name, pb.name, heads);
    if (caseId !== state.caseId) return; // the user moved on to another case
    ui.matchResult.classList.remove('error');
    ui.matchResult.append(describeMatch(m));
    setStatus(ui.pickStatus, `matched from heads [${heads.join(', ')}]`);
    if (m.transform) showPair(pa.name, pb.name, m.transform);
    document.body.dataset.match = 'done';
  } catch (err) {
    ui.matchResult.classList.add('error');
    ui.matchResult.textContent = err.message;
    setStatus(ui.pickStatus, 'the match failed', true);
    document.body.dataset.match = 'error';
  }
}

// --- assembly jobs -------------------------------------------------------------------

ui.assembleBtn.addEventListener('click', async () => {
  ui.assembleBtn.disabled = true;
  try {
    const job = await api.postAssemble(state.caseId);
    followJob(job);
  } catch (err) {
    setStatus(ui.jobStatus, err.message, true);
    ui.assembleBtn.disabled = !state.capabilities.assemble;
  }
});

function followJob(job) {
  ui.assembleBtn.disabled = true;
  ui.jobProgress.hidden = false;
  ui.jobProgress.removeAttribute('value'); // indeterminate until counts arrive
  setStatus(ui.jobStatus, `assembling ${job.case}…`);
  api.progressStream(job.job, (s) => {
    if (s.state === 'running') {
      if (s.total) {
        ui.jobProgress.max = s.total;
        ui.jobProgress.value = s.done ?? 0;
      } else {
        ui.jobProgress.removeAttribute('value');
      }
      const counts = s.total ? ` ${s.done ?? 0}/${s.total}` : '';
      setStatus(ui.jobStatus, `${s.case}: ${s.stage}${counts} ${s.message || ''} (${s.elapsed_s.toFixed(0)} s)`);
      return;
    }
    ui.jobProgress.hidden = true;
    ui.assembleBtn.disabled = !state.capabilities.assemble;
    if (s.state === 'done') {
      const r = s.result || {};
      setStatus(ui.jobStatus, `${s.case}: assembled in ${s.elapsed_s.toFixed(1)} s` +
        (r.placed !== undefined ? ` (${r.placed}/${r.fragments} placed, ${r.groups} groups)` : ''));
      document.body.dataset.job = 'done';
      if (s.case === state.caseId) loadCase(state.caseId);
      refreshCaseLabels();
    } else if (s.state === 'failed') {
      setStatus(ui.jobStatus, `${s.case || 'assembly'} failed: ${s.error}`, true);
      document.body.dataset.job = 'failed';
    }
  });
}

async function refreshCaseLabels() {
  try {
    const cases = await api.getCases();
    for (const c of cases.cases) {
      const opt = [...ui.caseSelect.options].find((o) => o.value === c.id);
      if (opt) opt.textContent = caseLabel(c);
    }
  } catch (_) { /* labels only */ }
}

init();
