// The three.js scene: fragments with their scattered and assembled poses, contours, picking.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

export const BACKGROUND = 0x1d2127;
const FRACTURE_TONE = new THREE.Color(0xc9bfae); // fracture faces: the fragment colour pulled toward this
const FRACTURE_MIX = 0.65;
const CONTOUR_COLOR = 0xffd23f;
const OTHER_CONTOUR_COLOR = 0x7fd6ff;
const GOLDEN = 0.381966;

export function fragmentColor(index) {
  // Hues spread by the golden angle: neighbours in the list never look alike.
  const hue = (0.03 + index * GOLDEN) % 1;
  return { hue, color: new THREE.Color().setHSL(hue, 0.62, 0.52) };
}

// Object groups and assembled pieces: the same golden-angle hues, a little darker and more
// saturated so that a group colour is not read as one fragment's; no group: grey.
export const NO_GROUP_COLOR = new THREE.Color(0x8a8a8a);

// How the assembly holds a placed fragment (relicgpu.heap.support): on a closed loop of matches,
// in a chain of them with no loop, or resting on one match alone; unplaced: grey.
const SUPPORT_COLORS = { loop: 0x3f9f4f, chain: 0xd8b13a, one: 0xd9602a };

export function supportColor(kind) {
  const hex = SUPPORT_COLORS[kind];
  return { hue: null, color: hex === undefined ? NO_GROUP_COLOR.clone() : new THREE.Color(hex) };
}
export function groupColor(group) {
  if (group === null || group === undefined) return { hue: null, color: NO_GROUP_COLOR.clone() };
  const hue = (0.03 + group * GOLDEN) % 1;
  return { hue, color: new THREE.Color().setHSL(hue, 0.75, 0.45) };
}

const IDENTITY_Q = new THREE.Quaternion();

export class FragmentScene {
  constructor(host) {
    this.host = host;
    this.renderer = new THREE.WebGLRenderer({ antialias: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setClearColor(BACKGROUND, 1);
    host.appendChild(this.renderer.domElement);

    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(35, 1, 0.001, 1000);
    this.camera.up.set(0, 0, 1); // scans and synthetic objects stand on z; OrbitControls reads this once
    this.scene.add(this.camera);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x505868, 1.6));
    const head = new THREE.DirectionalLight(0xffffff, 1.6); // a headlight: every side the user turns to is lit
    head.position.set(0.4, 0.8, 1);
    this.camera.add(head);

    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = false;
    this.controls.addEventListener('change', () => this.requestRender());

    this.fragments = new Map(); // name -> record
    this.blend = 1; // 0 scattered ... 1 assembled
    this.explode = 0;
    this.showContours = true;
    this.showFracture = true;
    this.pair = null; // {a, b, transform: Matrix4|null} while a pair is shown alone
    this.animation = null;
    this.renderPending = false;
    this.onAnimationEnd = null;

    new ResizeObserver(() => this.resize()).observe(host);
    this.resize();
  }

  resize() {
    const w = Math.max(1, this.host.clientWidth), h = Math.max(1, this.host.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  requestRender() {
    if (this.renderPending) return;
    this.renderPending = true;
    requestAnimationFrame(() => {
      this.renderPending = false;
      this.renderer.render(this.scene, this.camera);
    });
  }

  clear() {
    for (const rec of this.fragments.values()) {
      this.scene.remove(rec.mesh);
      rec.mesh.traverse((o) => {
        if (o.geometry) o.geometry.dispose();
        if (o.material) o.material.dispose();
      });
    }
    this.fragments.clear();
    this.pair = null;
    this.requestRender();
  }

  // mesh: {vertices Float32Array (V*3), faces Uint32Array (F*3), centroid [3], size}; pose: 16 numbers row-major or null
  addFragment(name, index, mesh, pose) {
    const { color, hue } = fragmentColor(index);
    const c = new THREE.Vector3(...mesh.centroid);
    const v = mesh.vertices, f = mesh.faces;
    const nf = f.length / 3;
    // Unindexed triangles: each face gets its own colour (fracture or original) and flat normal.
    const pos = new Float32Array(nf * 9);
    let radius = 0;
    for (let i = 0; i < f.length; i++) {
      const k = f[i] * 3;
      const x = v[k] - c.x, y = v[k + 1] - c.y, z = v[k + 2] - c.z;
      pos[i * 3] = x; pos[i * 3 + 1] = y; pos[i * 3 + 2] = z;
      radius = Math.max(radius, x * x + y * y + z * z);
    }
    const geom = new THREE.BufferGeometry();
    geom.setAttribute('position', new THREE.BufferAttribute(pos, 3));
    geom.setAttribute('color', new THREE.BufferAttribute(new Float32Array(nf * 9), 3));
    geom.computeVertexNormals();
    const material = new THREE.MeshStandardMaterial({
      vertexColors: true, roughness: 0.85, metalness: 0.0, side: THREE.DoubleSide,
      polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1, // contour lines stay on top
    });
    const obj = new THREE.Mesh(geom, material);
    obj.name = name;
    obj.matrixAutoUpdate = true;
    this.scene.add(obj);

    const rec = {
      name, index, color, hue, mesh: obj, centroid: c, radius: Math.sqrt(radius), size: mesh.size,
      nFaces: nf, faceRegion: null, regionIsFracture: null, contours: null, contourGroup: null,
      visible: true, markers: [],
      assembledQ: new THREE.Quaternion(), assembledP: c.clone(), placed: false, group: null,
      layoutP: c.clone(), layoutQ: new THREE.Quaternion(),
    };
    if (pose) {
      const m = new THREE.Matrix4().set(...pose);
      const s = new THREE.Vector3();
      m.decompose(new THREE.Vector3(), rec.assembledQ, s);
      rec.assembledP = c.clone().applyMatrix4(m);
      rec.placed = true;
    }
    this.fragments.set(name, rec);
    this.paintFaces(rec);
    return rec;
  }

  // Colour one fragment (a THREE.Color); its fracture faces keep their shading.
  setColor(name, color) {
    const rec = this.fragments.get(name);
    if (!rec) return;
    rec.color = color.clone();
    this.paintFaces(rec);
  }

  paintFaces(rec) {
    const attr = rec.mesh.geometry.getAttribute('color');
    const colors = attr.array;
    const broken = rec.color.clone().lerp(FRACTURE_TONE, FRACTURE_MIX);
    const shade = this.showFracture && rec.faceRegion && rec.faceRegion.length === rec.nFaces;
    for (let fi = 0; fi < rec.nFaces; fi++) {
      const frac = shade && rec.regionIsFracture[rec.faceRegion[fi]] === true;
      const col = frac ? broken : rec.color;
      for (let j = 0; j < 3; j++) {
        const o = (fi * 3 + j) * 3;
        colors[o] = col.r; colors[o + 1] = col.g; colors[o + 2] = col.b;
      }
    }
    attr.needsUpdate = true;
    this.requestRender();
  }

  // data: the /contours response
  setContours(name, data) {
    const rec = this.fragments.get(name);
    if (!rec) return;
    rec.faceRegion = data.face_region;
    rec.regionIsFracture = data.region_is_fracture;
    rec.contours = data.contours.map((ct) => ({
      ...ct,
      local: ct.points.map((p) => new THREE.Vector3(p[0] - rec.centroid.x, p[1] - rec.centroid.y, p[2] - rec.centroid.z)),
    }));
    if (rec.contourGroup) {
      rec.mesh.remove(rec.contourGroup);
      rec.contourGroup.traverse((o) => { if (o.geometry) o.geometry.dispose(); if (o.material) o.material.dispose(); });
    }
    const group = new THREE.Group();
    for (const ct of rec.contours) {
      if (ct.local.length < 2) continue;
      const g = new THREE.BufferGeometry().setFromPoints(ct.local);
      const line = new THREE.LineLoop(g, new THREE.LineBasicMaterial({
        color: ct.fracture === false ? OTHER_CONTOUR_COLOR : CONTOUR_COLOR,
      }));
      line.renderOrder = 1;
      group.add(line);
    }
    group.visible = this.showContours;
    rec.contourGroup = group;
    rec.mesh.add(group);
    this.paintFaces(rec);
  }

  setShowContours(on) {
    this.showContours = on;
    for (const rec of this.fragments.values()) if (rec.contourGroup) rec.contourGroup.visible = on;
    this.requestRender();
  }

  setShowFracture(on) {
    this.showFracture = on;
    for (const rec of this.fragments.values()) this.paintFaces(rec);
  }

  // Where each fragment sits when assembled: groups side by side, unplaced fragments in a row after them.
  layout() {
    const recs = [...this.fragments.values()];
    const groups = new Map();
    for (const r of recs) {
      if (!r.placed) continue;
      const g = r.group ?? -1;
      if (!groups.has(g)) groups.set(g, []);
      groups.get(g).push(r);
    }
    let cursor = null; // x of the right edge of what is laid out so far
    const gap = (r) => 0.5 * r;
    for (const members of groups.values()) {
      const sphere = sphereOf(members.map((r) => [r.assembledP, r.radius]));
      let shift = new THREE.Vector3();
      if (cursor !== null) shift.set(cursor + gap(sphere.radius) + sphere.radius - sphere.center.x, 0, 0);
      for (const r of members) {
        r.groupCenter = sphere.center.clone().add(shift);
        r.layoutP = r.assembledP.clone().add(shift);
        r.layoutQ = r.assembledQ.clone();
      }
      cursor = sphere.center.x + shift.x + sphere.radius;
    }
    const unplaced = recs.filter((r) => !r.placed);
    for (const r of unplaced) {
      if (cursor === null) {
        r.layoutP = r.centroid.clone();
        cursor = r.centroid.x + r.radius;
      } else {
        r.layoutP = new THREE.Vector3(cursor + gap(r.radius) + r.radius, r.centroid.y, r.centroid.z);
        cursor = r.layoutP.x + r.radius;
      }
      r.layoutQ = new THREE.Quaternion();
      r.groupCenter = r.layoutP.clone();
    }
    this.applyPoses();
  }

  setBlend(t) {
    this.blend = Math.min(1, Math.max(0, t));
    this.applyPoses();
  }

  setExplode(e) {
    this.explode = Math.max(0, e);
    this.applyPoses();
  }

  applyPoses() {
    const t = this.blend;
    for (const rec of this.fragments.values()) {
      const m = rec.mesh;
      if (this.pair) {
        const inPair = rec.name === this.pair.a || rec.name === this.pair.b;
        m.visible = inPair;
        if (!inPair) continue;
        if (rec.name === this.pair.a || !this.pair.transform) {
          m.quaternion.identity();
          m.position.copy(rec.centroid);
          if (rec.name === this.pair.b && !this.pair.transform) {
            const a = this.fragments.get(this.pair.a);
            m.position.x = a.centroid.x + a.radius + rec.radius * 1.2; // no pose: side by side
          }
        } else {
          const q = new THREE.Quaternion(), s = new THREE.Vector3();
          this.pair.transform.decompose(new THREE.Vector3(), q, s);
          m.quaternion.copy(q);
          m.position.copy(rec.centroid).applyMatrix4(this.pair.transform);
        }
        continue;
      }
      m.visible = rec.visible;
      const target = rec.layoutP.clone();
      if (rec.placed && this.explode > 0) {
        target.add(rec.layoutP.clone().sub(rec.groupCenter).multiplyScalar(this.explode));
      }
      m.quaternion.slerpQuaternions(IDENTITY_Q, rec.layoutQ, t);
      m.position.lerpVectors(rec.centroid, target, t);
    }
    this.requestRender();
  }

  animateBlend(to, ms = 900, everyFrame = null) {
    const from = this.blend;
    const start = performance.now();
    if (this.animation) cancelAnimationFrame(this.animation);
    const step = (now) => {
      const u = Math.min(1, (now - start) / ms);
      const eased = u < 0.5 ? 2 * u * u : 1 - Math.pow(-2 * u + 2, 2) / 2;
      this.setBlend(from + (to - from) * eased);
      if (everyFrame) everyFrame(this.blend);
      if (u < 1) {
        this.animation = requestAnimationFrame(step);
      } else {
        this.animation = null;
        if (this.onAnimationEnd) this.onAnimationEnd();
      }
    };
    this.animation = requestAnimationFrame(step);
  }

  shownRecords() {
    return [...this.fragments.values()].filter((r) => r.mesh.visible);
  }

  // Point the camera at what is shown (or at the named fragments), keeping the viewing direction.
  fit(names = null) {
    const recs = names ? names.map((n) => this.fragments.get(n)).filter(Boolean) : this.shownRecords();
    if (!recs.length) return;
    for (const r of recs) r.mesh.updateMatrixWorld(true);
    const sphere = sphereOf(recs.map((r) => [r.mesh.position, r.radius]));
    const dir = this.camera.position.clone().sub(this.controls.target);
    if (dir.lengthSq() < 1e-12 || !this.fitted) dir.set(0.55, -0.9, 0.6); // a first view from the front, above
    dir.normalize();
    const fov = THREE.MathUtils.degToRad(this.camera.fov);
    const half = Math.min(fov, 2 * Math.atan(Math.tan(fov / 2) * this.camera.aspect)) / 2;
    const dist = (sphere.radius * 1.08) / Math.sin(half);
    this.controls.target.copy(sphere.center);
    this.camera.position.copy(sphere.center).addScaledVector(dir, dist);
    this.camera.near = Math.max(dist / 1000, dist - sphere.radius * 4) * 0.1;
    this.camera.far = dist + sphere.radius * 10;
    this.camera.updateProjectionMatrix();
    this.controls.update();
    this.fitted = true;
    this.requestRender();
  }

  setVisible(name, on) {
    const rec = this.fragments.get(name);
    if (!rec) return;
    rec.visible = on;
    this.applyPoses();
  }

  showPair(a, b, transform) {
    this.pair = { a, b, transform: transform ? new THREE.Matrix4().set(...transform.flat()) : null };
    this.applyPoses();
  }

  clearPair() {
    this.pair = null;
    this.applyPoses();
  }

  // The contour point nearest to a click, on the fragment under the cursor when there is one.
  pickContourPoint(clientX, clientY, maxPixels = 16) {
    const rect = this.renderer.domElement.getBoundingClientRect();
    const ndc = new THREE.Vector2(((clientX - rect.left) / rect.width) * 2 - 1, -((clientY - rect.top) / rect.height) * 2 + 1);
    const ray = new THREE.Raycaster();
    ray.setFromCamera(ndc, this.camera);
    const shown = this.shownRecords().filter((r) => r.contours);
    const hits = ray.intersectObjects(shown.map((r) => r.mesh), false);
    const candidates = hits.length ? [this.fragments.get(hits[0].object.name)] : shown;
    let best = null;
    const p = new THREE.Vector3();
    for (const rec of candidates) {
      rec.mesh.updateMatrixWorld(true);
      rec.contours.forEach((ct, ci) => {
        ct.local.forEach((lp, pi) => {
          p.copy(lp).applyMatrix4(rec.mesh.matrixWorld).project(this.camera);
          const sx = ((p.x + 1) / 2) * rect.width + rect.left, sy = ((1 - p.y) / 2) * rect.height + rect.top;
          const d = Math.hypot(sx - clientX, sy - clientY);
          if (d <= maxPixels && p.z < 1 && (!best || d < best.pixels)) best = { name: rec.name, contour: ci, point: pi, pixels: d };
        });
      });
    }
    return best;
  }

  // Screen position of a contour point (used by the browser test to click like a user).
  screenPositionOf(name, contour, point) {
    const rec = this.fragments.get(name);
    if (!rec || !rec.contours || !rec.contours[contour]) return null;
    rec.mesh.updateMatrixWorld(true);
    const p = rec.contours[contour].local[point].clone().applyMatrix4(rec.mesh.matrixWorld).project(this.camera);
    const rect = this.renderer.domElement.getBoundingClientRect();
    return { x: ((p.x + 1) / 2) * rect.width + rect.left, y: ((1 - p.y) / 2) * rect.height + rect.top };
  }

  addMarker(name, contour, point) {
    const rec = this.fragments.get(name);
    if (!rec) return;
    const geom = new THREE.SphereGeometry(Math.max(rec.radius * 0.035, 1e-6), 16, 12);
    const marker = new THREE.Mesh(geom, new THREE.MeshBasicMaterial({ color: 0xffffff, depthTest: false }));
    marker.renderOrder = 2;
    marker.position.copy(rec.contours[contour].local[point]);
    rec.mesh.add(marker);
    rec.markers.push(marker);
    this.requestRender();
  }

  clearMarkers() {
    for (const rec of this.fragments.values()) {
      for (const m of rec.markers) {
        rec.mesh.remove(m);
        m.geometry.dispose();
        m.material.dispose();
      }
      rec.markers = [];
    }
    this.requestRender();
  }

  flash(name) {
    const rec = this.fragments.get(name);
    if (!rec) return;
    rec.mesh.material.emissive.setHex(0x553311);
    this.requestRender();
    setTimeout(() => { rec.mesh.material.emissive.setHex(0x000000); this.requestRender(); }, 600);
  }
}

// A sphere holding spheres [center Vector3, radius]: centred on the box of their extents.
function sphereOf(items) {
  const box = new THREE.Box3();
  for (const [c, r] of items) {
    box.expandByPoint(c.clone().addScalar(-r));
    box.expandByPoint(c.clone().addScalar(r));
  }
  const center = box.getCenter(new THREE.Vector3());
  let radius = 0;
  for (const [c, r] of items) radius = Math.max(radius, c.distanceTo(center) + r);
  return { center, radius: Math.max(radius, 1e-9) };
}
