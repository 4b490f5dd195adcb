// splatdeform editor page: the paper's loop in the browser. The model and, once per fit, its
// basis (values + gradients per point) live in GPU buffers; a pose is delta C = T(C) - C
// (12 floats per handle) in uniforms, and the vertex shaders deform points, meshes and Gaussians.
// The Python server keeps the editor state (regions, fit, poses, undo, save); a pose message
// to it is 16 numbers and is not waited for.
import * as THREE from 'three';
import { OrbitControls } from '/web/vendor/OrbitControls.js';
import { TransformControls } from '/web/vendor/TransformControls.js';

const TOKEN = new URLSearchParams(location.search).get('t') || '';
const $ = (id) => document.getElementById(id);
const stats = { poses: 0, lastPoseMs: 0, lastDrawMs: 0, frames: 0, poseBytes: 0, sortMs: 0 };
window.sdStats = stats;

async function api(path, asBytes) {
  const r = await fetch(path, { headers: { 'X-Editor-Token': TOKEN } });
  if (!r.ok) throw new Error(`${path}: ${r.status}`);
  return asBytes ? r.arrayBuffer() : r.json();
}

// Actions reach the server one at a time, in the order they were made (the server answers each
// request on its own thread: three quick size edits could otherwise land in any order).
let actions = Promise.resolve();
function act(req, quiet) {
  const body = JSON.stringify(req);  // the request as it is now, whatever runs before it
  const run = () => send(req, body, quiet);
  const done = actions.then(run, run);
  actions = done.catch(() => {});
  return done;
}

async function send(req, body, quiet) {
  if (req.op === 'pose') stats.poseBytes = body.length;
  const r = await fetch('/api/action', {
    method: 'POST', body, headers: { 'X-Editor-Token': TOKEN, 'Content-Type': 'application/json' } });
  const out = await r.json();
  if (out.error) $('status').textContent = out.error;
  else if (!quiet) $('status').textContent = out.message || '';
  return out;
}

const shaderText = {};
async function loadShaders() {
  for (const name of ['deform.glsl', 'shading.glsl', 'points.vert', 'points.frag', 'mesh.frag',
                      'gauss.vert', 'gauss.frag', 'parity.vert', 'covariance_page.glsl']) {
    const r = await fetch(`/web/shaders/${name}`);
    shaderText[name] = await r.text();
  }
  // the covariance modes come from shaders/covariance.glsl itself (the renderer's source)
  shaderText['covariance.glsl'] = await (await fetch('/web/shared/covariance.glsl')).text();
}
const COVARIANCE_MODES = ['jacobian', 'rotation', 'limited'];  // gaussians.covariance
const covarianceDefine = (mode) => Math.max(COVARIANCE_MODES.indexOf(mode || 'limited'), 0);

function source(defines, ...names) {
  const head = Object.entries(defines).map(([k, v]) => `#define ${k} ${v}`).join('\n');
  return `precision highp float;\nprecision highp int;\n${head}\n${names.map((n) => shaderText[n]).join('\n')}`;
}

// An RGBA32F texture holding `data` (length a multiple of 4) in rows of at most 4096 texels.
function floatTexture(data) {
  const texels = Math.max(1, data.length / 4);
  const width = Math.min(4096, texels);
  const height = Math.ceil(texels / width);
  const padded = new Float32Array(width * height * 4);
  padded.set(data);
  const tex = new THREE.DataTexture(padded, width, height, THREE.RGBAFormat, THREE.FloatType);
  tex.minFilter = tex.magFilter = THREE.NearestFilter;
  tex.needsUpdate = true;
  return { tex, width };
}

// ---- state -------------------------------------------------------------------------------
const S = {
  scene: null, state: null, arrays: {}, labels: null,
  fit: { id: -1, k: 0, basis: null, control: null, tex: null, width: 1 },
  poses: [], delta: new Float32Array(0), selected: null, placing: null, activeHandle: 0,
  sortKey: '', needSort: true,
};

const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
const gl = renderer.getContext();
$('view').appendChild(renderer.domElement);
const scene3 = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(35, 1, 0.01, 100);
const orbit = new OrbitControls(camera, renderer.domElement);
const gizmo = new TransformControls(camera, renderer.domElement);
gizmo.setSize(0.8);
const gizmoTarget = new THREE.Object3D();
scene3.add(gizmoTarget);
scene3.add(gizmo);
const outlines = new THREE.Group();
scene3.add(outlines);
let model = null;       // THREE.Points | THREE.Mesh | THREE.Mesh (instanced splats)
let material = null;

function resize() {
  const el = $('view');
  renderer.setSize(el.clientWidth, el.clientHeight);
  camera.aspect = el.clientWidth / Math.max(el.clientHeight, 1);
  camera.updateProjectionMatrix();
  requestDraw();
}
window.addEventListener('resize', resize);

// ---- model upload (once) -----------------------------------------------------------------
const TYPES = { '<f4': Float32Array, '|u1': Uint8Array, '<u4': Uint32Array };

async function loadArrays() {
  for (const [name, meta] of Object.entries(S.scene.arrays)) {
    const buf = await api(`/api/array/${name}`, true);
    S.arrays[name] = new TYPES[meta.dtype](buf);
  }
}

function baseUniforms() {
  return {
    u_basis: { value: null }, u_basis_width: { value: 1 }, u_delta: { value: [] },
    u_show_regions: { value: 1.0 }, u_size: { value: S.scene.point_size },
    u_px: { value: 500 }, u_has_normals: { value: S.arrays.normals ? 1.0 : 0.0 },
    u_splat: { value: null }, u_splat_width: { value: 1 }, u_sh: { value: null },
    u_sh_width: { value: 1 }, u_order: { value: null }, u_order_width: { value: 1 }, u_viewport: { value: new THREE.Vector2(1, 1) },
  };
}

function shTexels() {
  const rest = S.arrays.sh_rest ? S.arrays.sh_rest.length / S.scene.n : 0;
  return Math.ceil(rest / 4);
}

function makeMaterial() {
  const K = S.fit.k;
  const kind = S.scene.kind;
  let vert, frag, extra = {};
  if (kind === 'splats') {
    const deg = S.scene.sh_degree;
    const defs = { K, SH_DEGREE: deg, SH_REST: Math.max((deg + 1) ** 2 - 1, 1), SH_TEXELS: Math.max(shTexels(), 1),
      COVARIANCE: covarianceDefine(S.scene.covariance) };
    vert = source(defs, 'deform.glsl', 'covariance.glsl', 'covariance_page.glsl', 'shading.glsl', 'gauss.vert');
    frag = source({}, 'gauss.frag');
    extra = { transparent: true, depthWrite: false, depthTest: false, blending: THREE.CustomBlending,
      blendSrc: THREE.OneFactor, blendDst: THREE.OneMinusSrcAlphaFactor };
  } else {
    vert = source({ K }, 'deform.glsl', 'shading.glsl', 'points.vert');
    frag = source({}, 'shading.glsl', kind === 'mesh' ? 'mesh.frag' : 'points.frag');
  }
  const old = material;
  material = new THREE.RawShaderMaterial({
    vertexShader: vert, fragmentShader: frag, glslVersion: THREE.GLSL3,
    uniforms: old ? old.uniforms : baseUniforms(), side: THREE.DoubleSide, ...extra });
  if (old) old.dispose();
  if (model) model.material = material;
  applyFitUniforms();
}

function splatTextureData() {
  const n = S.scene.n, a = S.arrays, out = new Float32Array(16 * n);
  for (let i = 0; i < n; i++) {
    const o = 16 * i;
    out[o] = a.positions[3 * i]; out[o + 1] = a.positions[3 * i + 1]; out[o + 2] = a.positions[3 * i + 2];
    out[o + 3] = a.colors[4 * i + 3] / 255;
    for (let j = 0; j < 6; j++) out[o + 4 + j] = a.cov6[6 * i + j];
    out[o + 10] = S.labels ? S.labels[i] : 0;
    out[o + 11] = a.shape[2 * i];  // log-scale spread and mean (covariance.glsl's shape)
    for (let j = 0; j < 3; j++) out[o + 12 + j] = a.colors[4 * i + j] / 255;
    out[o + 15] = a.shape[2 * i + 1];
  }
  return out;
}

function buildModel() {
  const a = S.arrays, n = S.scene.n, kind = S.scene.kind;
  makeMaterial();
  if (kind === 'splats') {
    // one plain draw of point sprites, one vertex per sorted slot, the splat index of a slot
    // from the order texture (per-instance draws are slow in software WebGL, and a quad of 4
    // vertices runs the per-splat maths 4 times)
    const quad = new THREE.BufferGeometry();
    quad.setAttribute('position', new THREE.BufferAttribute(new Float32Array(n), 1));  // the count
    quad.boundingSphere = new THREE.Sphere(new THREE.Vector3(), Infinity);  // never culled
    S.order = new Float32Array(4 * Math.ceil(n / 4));
    for (let i = 0; i < n; i++) S.order[i] = i;
    const ot = floatTexture(S.order);
    S.orderTex = ot.tex;
    material.uniforms.u_order.value = ot.tex; material.uniforms.u_order_width.value = ot.width;
    const sp = floatTexture(splatTextureData());
    material.uniforms.u_splat.value = sp.tex; material.uniforms.u_splat_width.value = sp.width;
    if (a.sh_rest) {
      const per = a.sh_rest.length / n, t = shTexels(), data = new Float32Array(n * t * 4);
      for (let i = 0; i < n; i++) data.set(a.sh_rest.subarray(i * per, (i + 1) * per), i * t * 4);
      const sh = floatTexture(data);
      material.uniforms.u_sh.value = sh.tex; material.uniforms.u_sh_width.value = sh.width;
    }
    model = new THREE.Points(quad, material);
  } else {
    const geo = new THREE.BufferGeometry();
    geo.setAttribute('position', new THREE.BufferAttribute(a.positions, 3));
    geo.setAttribute('normal', new THREE.BufferAttribute(a.normals || new Float32Array(3 * n), 3));
    geo.setAttribute('color', new THREE.BufferAttribute(a.colors, 4, true));
    geo.setAttribute('label', new THREE.BufferAttribute(new Float32Array(n), 1));
    if (kind === 'mesh') {
      geo.setIndex(new THREE.BufferAttribute(a.faces, 1));
      model = new THREE.Mesh(geo, material);
    } else {
      model = new THREE.Points(geo, material);
    }
  }
  model.frustumCulled = false;
  scene3.add(model);
}

function applyFitUniforms() {
  if (!material) return;
  const u = material.uniforms;
  u.u_basis.value = S.fit.tex; u.u_basis_width.value = S.fit.width;
  const K = S.fit.k, list = [];
  for (let k = 0; k < K; k++) list.push(new THREE.Vector3(S.delta[3 * k], S.delta[3 * k + 1], S.delta[3 * k + 2]));
  u.u_delta.value = list;
}

// ---- the per-pose path: delta C from the poses, in uniforms ------------------------------
function affine(m, p) {  // m: 4x4 row-major nested list
  return [0, 1, 2].map((r) => m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]);
}

function computeDelta() {
  const K = S.fit.k, d = new Float32Array(3 * K);
  const live = S.state && !S.state.stale && S.fit.basis;
  if (live) {
    const H = S.fit.control.length;  // the handles' columns (4 each), then the curve's
    for (let k = 0; k < H; k++) {
      const c = S.fit.control[k], t = affine(S.poses[Math.floor(k / 4)], c);
      for (let j = 0; j < 3; j++) d[3 * k + j] = t[j] - c[j];
    }
    const cv = S.state.curve;
    const C = cv ? cv.control.length : 0;
    for (let k = H; cv && k < H + C && k < K; k++) {  // delta = moved_to - control point
      for (let j = 0; j < 3; j++) d[3 * k + j] = cv.moved[k - H][j] - cv.control[k - H][j];
    }
    const pt = S.state.points;  // control-point pairs: the last 3 columns, delta = g I
    if (pt && pt.delta && K >= H + C + 3) {
      for (let r = 0; r < 3; r++) for (let j = 0; j < 3; j++) d[3 * (K - 3 + r) + j] = pt.delta[r][j];
    }
  }
  S.delta = d;
  applyFitUniforms();
  S.needSort = true;
}

// ---- the curve: control points (blue), their moved points (orange), the moved curve --------
const curveGroup = new THREE.Group();
scene3.add(curveGroup);
// What `deform` prints after a fit: method, centers, constraints (kept), boundary error
// (largest |r| over the kept constraints, model units) and the region counts.
function fitFigures(st) {
  const f = st.fit && st.fit.stats;
  if (!f || !('centers' in f)) return '';
  const n = (v) => (typeof v === 'number' ? v.toLocaleString('en-US') : String(v));
  // 3 significant digits (0.000495, 1.2e-7), a zero as 0 (toPrecision gives '0.00')
  const g = (v) => (typeof v !== 'number' ? String(v) : v === 0 ? '0' : String(+v.toPrecision(3)));
  const kept = f.kept !== undefined && f.kept !== null && f.kept !== f.constraints ? ` (kept ${n(f.kept)})` : '';
  const c = st.counts || {};
  return `method ${f.method} · centers ${n(f.centers)}\n` +
    `constraints ${n(f.constraints)}${kept}\n` +
    `boundary error ${g(f.residual)}${kept ? ' over the kept constraints' : ''} (tolerance ${g(f.tolerance)}${f.converged === false ? ', not converged' : ''})\n` +
    `regions: fixed ${n(c.fixed)} · handle ${n(c.handle)} · free ${n(c.free)}` +
    (f.seconds !== undefined ? ` · ${g(f.seconds)} s` : '');
}

function curveDelta() {  // the curve's rows of delta C (k_curve x 3), zeros without a live fit
  const cv = S.state && S.state.curve, k = cv ? cv.control.length : 0, H = S.fit.control ? S.fit.control.length : 0;
  const live = S.state && !S.state.stale && S.fit.basis && S.fit.k === H + k + (S.state.points ? 3 : 0);
  return Array.from({ length: k }, (_, i) => [0, 1, 2].map((j) => (live ? cv.moved[i][j] - cv.control[i][j] : 0)));
}
function renderCurve() {
  for (const o of [...curveGroup.children]) { curveGroup.remove(o); o.geometry.dispose(); o.material.dispose(); }
  const cv = S.state && S.state.curve;
  if (!cv) return;
  const dot = (pts, color) => {
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(new Float32Array(pts.flat()), 3));
    return new THREE.Points(g, new THREE.PointsMaterial({ color, size: 9, sizeAttenuation: false, depthTest: false }));
  };
  curveGroup.add(dot(cv.control, 0x2050ff));
  curveGroup.add(dot(cv.moved, 0xff781e));
  if (cv.samples.length) {  // the moved curve: samples + weights . delta
    const dC = curveDelta();
    const pts = cv.samples.map((p, s) => [0, 1, 2].map((j) => p[j] + cv.weights[s].reduce((a, w, i) => a + w * dC[i][j], 0)));
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(new Float32Array(pts.flat()), 3));
    curveGroup.add(new THREE.Line(g, new THREE.LineBasicMaterial({ color: 0xff781e, depthTest: false })));
  }
}

// ---- control-point pairs: arrows source -> target (magenta, before), and with a current fit
// where the field sends each source (green dots, after; on the targets for an exact fit)
const pairsGroup = new THREE.Group();
scene3.add(pairsGroup);
function renderPairs() {
  for (const o of [...pairsGroup.children]) { pairsGroup.remove(o); o.geometry.dispose(); o.material.dispose(); }
  let pt = S.state && S.state.points;
  if (!pt) return;
  const d = S.pairDrag;  // a pair's end under the gizmo, drawn where it is dragged
  if (d && d.index < pt.n) {
    const key = d.end === 'source' ? 'sources' : 'targets';
    pt = { ...pt, [key]: pt[key].map((p, i) => (i === d.index ? d.at : p)) };
  }
  const seg = new Float32Array(6 * pt.n);
  for (let i = 0; i < pt.n; i++) seg.set([...pt.sources[i], ...pt.targets[i]], 6 * i);
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(seg, 3));
  pairsGroup.add(new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: 0xe600c8, depthTest: false })));
  const dot = (pts, color) => {
    const q = new THREE.BufferGeometry();
    q.setAttribute('position', new THREE.BufferAttribute(new Float32Array(pts.flat()), 3));
    return new THREE.Points(q, new THREE.PointsMaterial({ color, size: 7, sizeAttenuation: false, depthTest: false }));
  };
  pairsGroup.add(dot(pt.sources, 0x141414));
  pairsGroup.add(dot(pt.targets, 0xe600c8));
  if (pt.after) pairsGroup.add(dot(pt.after, 0x14a028));
}

// P + B delta C on the CPU (depth-sort keys and picking); positions when there is no fit.
function deformedPositions() {
  const p = S.arrays.positions;
  const K = S.fit.k, b = S.fit.basis, d = S.delta;
  if (!b || !K || !d.some((v) => v !== 0)) return p;
  const n = S.scene.n, out = new Float32Array(3 * n), stride = 4 * K;
  for (let i = 0; i < n; i++) {
    let x = p[3 * i], y = p[3 * i + 1], z = p[3 * i + 2];
    const o = i * stride;
    for (let k = 0; k < K; k++) {
      const w = b[o + k];
      if (w !== 0) { x += w * d[3 * k]; y += w * d[3 * k + 1]; z += w * d[3 * k + 2]; }
    }
    out[3 * i] = x; out[3 * i + 1] = y; out[3 * i + 2] = z;
  }
  return out;
}
window.sdDeformedPositions = () => Array.from(deformedPositions());

// Back-to-front order of the splats by view depth: 16-bit counting sort of P + B dC.
function sortSplats() {
  if (S.scene.kind !== 'splats') return;
  const t0 = performance.now();
  camera.updateMatrixWorld();
  const e = camera.matrixWorldInverse.elements;
  const key = `${e.join(',')}|${Array.from(S.delta).join(',')}`;
  if (!S.needSort && key === S.sortKey) return;
  const p = deformedPositions(), n = S.scene.n;
  const depth = new Float32Array(n);
  let lo = Infinity, hi = -Infinity;
  for (let i = 0; i < n; i++) {
    const z = e[2] * p[3 * i] + e[6] * p[3 * i + 1] + e[10] * p[3 * i + 2] + e[14];
    depth[i] = z; if (z < lo) lo = z; if (z > hi) hi = z;
  }
  const scale = 65535 / Math.max(hi - lo, 1e-12), counts = new Uint32Array(65537);
  const bucket = new Uint16Array(n);
  for (let i = 0; i < n; i++) { bucket[i] = (depth[i] - lo) * scale; counts[bucket[i] + 1]++; }
  for (let i = 1; i < 65537; i++) counts[i] += counts[i - 1];
  for (let i = 0; i < n; i++) S.order[counts[bucket[i]]++] = i;  // most negative z (far) first
  S.orderTex.image.data.set(S.order);
  S.orderTex.needsUpdate = true;
  S.sortKey = key; S.needSort = false;
  stats.sortMs = performance.now() - t0;
}

// ---- drawing and frame timing ------------------------------------------------------------
let drawQueued = false;
const pixel = new Uint8Array(4);
let pendingInput = null;  // performance.now() timestamp of the input a frame answers
function requestDraw(inputTime) {
  if (inputTime !== undefined && pendingInput === null) pendingInput = inputTime;
  if (drawQueued) return;
  drawQueued = true;
  requestAnimationFrame(draw);
}

function draw() {
  drawQueued = false;
  const t0 = performance.now();
  const size = renderer.getSize(new THREE.Vector2());
  if (material) {
    material.uniforms.u_viewport.value.set(size.x, size.y);
    material.uniforms.u_px.value = 0.5 * size.y * camera.projectionMatrix.elements[5];
    material.uniforms.u_size.value = S.scene.point_size * Number($('psize').value);
  }
  sortSplats();
  renderer.render(scene3, camera);
  gl.finish();
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);  // a true fence: finish alone
  // returned before software WebGL had drawn (measured), a read-back cannot
  stats.frames++;
  stats.lastDrawMs = performance.now() - t0;
  if (pendingInput !== null) {
    const start = pendingInput;
    pendingInput = null;
    requestAnimationFrame(() => {  // the animation frame after the draw
      stats.lastPoseMs = performance.now() - start;
      stats.poses++;
      showStats();
    });
  }
  showStats();
}

function showStats() {
  $('stats').textContent = `draw ${stats.lastDrawMs.toFixed(1)} ms · pose→frame ${stats.lastPoseMs.toFixed(1)} ms` +
    `\nsort ${stats.sortMs.toFixed(1)} ms · pose message ${stats.poseBytes} B`;
}

// Benchmark hook: apply a local pose to handle h as a drag would, resolve with the pose-to-
// frame time measured in the page (input time to the animation frame after the finished draw).
window.sdBenchPose = (matrix, h = 0) => new Promise((resolve) => {
  const t = performance.now();
  const before = stats.poses;
  setPose(h, matrix, false, t);
  const poll = () => (stats.poses > before ? resolve(stats.lastPoseMs) : setTimeout(poll, 1));
  poll();
});

// ---- state from the server ---------------------------------------------------------------
async function applyState(st) {
  if (!st || !st.selectors) return;
  S.state = st;
  S.poses = st.poses;
  if (S.scene.kind === 'splats' && st.covariance && st.covariance !== S.scene.covariance) {
    S.scene.covariance = st.covariance;  // gaussians.covariance changed (or undone): recompile
    makeMaterial();
  }
  if (st.fit && st.fit.id !== S.fit.id) {
    const buf = await api('/api/basis', true);
    const basis = new Float32Array(buf);
    if (S.fit.tex) S.fit.tex.dispose();
    const t = floatTexture(basis);
    S.fit = { id: st.fit.id, k: st.fit.k, basis, control: st.fit.control, tex: t.tex, width: t.width };
    makeMaterial();
  }
  const labels = new Uint8Array(await api('/api/labels', true));
  S.labels = labels;
  if (S.scene.kind === 'splats') {
    const sp = floatTexture(splatTextureData());
    material.uniforms.u_splat.value.dispose();
    material.uniforms.u_splat.value = sp.tex;
  } else {
    const attr = model.geometry.getAttribute('label');
    for (let i = 0; i < labels.length; i++) attr.array[i] = labels[i];
    attr.needsUpdate = true;
  }
  computeDelta();
  const c = st.counts;
  $('counts').textContent = `fixed ${c.fixed} · handle ${c.handle} · free ${c.free} of ${S.scene.n}` +
    (st.problem ? `\n⚠ ${st.problem}` : '');
  $('fitinfo').textContent = !st.fit ? 'no fit yet: mark fixed and handle regions, then Fit'
    : st.stale ? 'fit is stale (regions changed): Fit again' : `fit current · k = ${st.fit.k} · drag the handle gizmo`;
  $('fitfigures').textContent = fitFigures(st) + (st.points ? `\npairs ${st.points.n}: arrows source → target (magenta)` +
    (st.points.after ? ', fitted sources green' : ', Fit moves the sources onto them') : '');
  $('undo').disabled = !st.can_undo; $('redo').disabled = !st.can_redo;
  const sel = $('active-handle');
  sel.innerHTML = '';
  for (let h = 0; h < st.handles; h++) sel.add(new Option(`adds to handle ${h}`, h));
  S.activeHandle = Math.min(S.activeHandle, st.handles - 1);
  sel.value = S.activeHandle;
  $('remove-handle').disabled = st.handles < 2;
  if (S.selected && S.selected.type === 'selector' && !findSelector(S.selected)) S.selected = null;
  if (S.selected && S.selected.type === 'pose' && (!st.fit || st.stale)) S.selected = null;
  if (S.selected && S.selected.type === 'curve' && (!st.curve || S.selected.index >= st.curve.control.length)) S.selected = null;
  if (S.selected && S.selected.type === 'pair' && (!st.points || S.selected.index >= st.points.n)) S.selected = null;
  if (!S.selected && st.fit && !st.stale) {  // the first handle's pose, else the curve's first point
    S.selected = st.fit.control.length ? { type: 'pose', handle: 0 } : st.curve ? { type: 'curve', index: 0 } : null;
  }
  renderTree();
  renderOutlines();
  renderCurve();
  renderPairs();
  applyPairInfo();
  const cv = st.curve;
  $('curveinfo').textContent = !cv ? 'no curve: click control points on the model'
    : `${cv.control.length} control points · band ${cv.band} points` + (cv.problem ? `\n⚠ ${cv.problem}` : '');
  if (cv && document.activeElement !== $('curve-radius')) $('curve-radius').value = +cv.capture_radius.toPrecision(6);
  if (cv) $('curve-degree').value = String(cv.degree);
  attachGizmo();
  requestDraw();
  S.shown = st;  // what sdState() reports: the state once it is on screen
}

function findSelector(ref) {
  return S.state.selectors.find((s) => s.role === ref.role && s.handle === ref.handle && s.index === ref.index);
}

// One selector's YAML as tree rows [depth, text]: all / not are inner nodes, the rest leaves.
function selectorRows(y, depth, out) {
  const [key, v] = Object.entries(y)[0];
  if (key === 'all') {
    out.push([depth, 'all (intersection)']);
    for (const part of v) selectorRows(part, depth + 1, out);
  } else if (key === 'not') {
    out.push([depth, 'not (complement)']);
    selectorRows(v, depth + 1, out);
  } else if (key === 'indices' && Array.isArray(v)) {
    out.push([depth, `indices (${v.length} points)`]);
  } else {
    out.push([depth, `${key} ${JSON.stringify(v)}`]);
  }
  return out;
}

const MAX_PAIR_ROWS = 200;  // pairs listed in the tree (any pair: click its dot on the view)
function renderTree() {
  const tree = $('tree');
  tree.innerHTML = '';
  const row = (depth, text, ref) => {
    const div = document.createElement('div');
    div.className = 'node';
    div.dataset.depth = depth;
    div.style.paddingLeft = `${12 * depth}px`;
    div.textContent = text;
    if (ref) {
      if (S.selected && ref.type === S.selected.type && ref.role === S.selected.role &&
          ref.handle === S.selected.handle && ref.index === S.selected.index) div.classList.add('sel');
      div.onclick = () => { S.selected = ref; renderTree(); attachGizmo(); applyPairInfo(); };
    }
    tree.appendChild(div);
  };
  const selectors = (list) => {
    for (const s of list) {
      const ref = { type: 'selector', role: s.role, handle: s.handle, index: s.index };
      for (const [depth, text] of selectorRows(s.yaml, 1, [])) row(depth, text, ref);
    }
  };
  row(0, 'fixed (union)');
  selectors(S.state.selectors.filter((s) => s.role === 'fixed'));
  for (let h = 0; h < S.state.handles; h++) {
    if (S.state.fit && !S.state.stale && 4 * h < S.state.fit.control.length) row(0, `handle ${h} (union) · pose gizmo`, { type: 'pose', handle: h });
    else row(0, `handle ${h} (union)`);
    selectors(S.state.selectors.filter((x) => x.role === 'handle' && x.handle === h));
  }
  const cv = S.state.curve;
  if (cv) {
    row(0, `curve (degree ${cv.degree}, band ${cv.band} points)`);
    const moving = S.state.fit && !S.state.stale;
    for (let i = 0; i < cv.control.length; i++) {
      row(1, `point ${i}${moving ? ' · drag its moved point' : ''}`, { type: 'curve', index: i });
    }
  }
  const pt = S.state.points;
  if (pt) {
    row(0, `control-point pairs (${pt.n})`);
    for (let i = 0; i < Math.min(pt.n, MAX_PAIR_ROWS); i++) row(1, `pair ${i}`, { type: 'pair', index: i });
    if (pt.n > MAX_PAIR_ROWS) row(1, `… ${pt.n - MAX_PAIR_ROWS} more: click a pair's dot on the view`);
  }
  const s = S.selected && S.selected.type === 'selector' ? findSelector(S.selected) : null;
  if (s && document.activeElement !== $('sel-text')) $('sel-text').value = JSON.stringify(s.yaml);
  for (const [i, id] of ['cx', 'cy', 'cz'].entries()) { $(id).value = s ? +s.center[i].toPrecision(6) : ''; $(id).disabled = !s; }
  for (const [i, id] of ['sx', 'sy', 'sz'].entries()) {
    $(id).value = s ? +s.size[i].toPrecision(6) : ''; $(id).disabled = !s || s.kind === 'plane' || (s.kind === 'sphere' && i > 0);
  }
}

function renderOutlines() {
  for (const o of [...outlines.children]) { outlines.remove(o); o.geometry.dispose(); o.material.dispose(); }
  for (const s of S.state.selectors) {
    if (s.kind === 'other') continue;
    const color = s.role === 'fixed' ? 0x326eff : 0xff781e;
    let geo;
    if (s.kind === 'box') geo = new THREE.EdgesGeometry(new THREE.BoxGeometry(...s.size.map((v) => Math.max(v, 1e-9))));
    else if (s.kind === 'sphere') geo = new THREE.WireframeGeometry(new THREE.IcosahedronGeometry(s.size[0], 2));
    else geo = new THREE.EdgesGeometry(new THREE.PlaneGeometry(0.8 * S.scene.diagonal, 0.8 * S.scene.diagonal));
    const line = new THREE.LineSegments(geo, new THREE.LineBasicMaterial({ color, depthTest: false }));
    line.position.fromArray(s.center);
    if (s.kind === 'plane') line.quaternion.setFromUnitVectors(new THREE.Vector3(0, 0, 1), new THREE.Vector3(...s.normal));
    line.userData = s;
    outlines.add(line);
  }
}

// ---- the one gizmo: on the selected item -------------------------------------------------
let drag = null;
function pivotOf(h) {
  return affine(S.poses[h], S.fit.control[4 * h]);
}

const pairEnd = () => $('pair-end').value;  // 'target' | 'source'
function attachGizmo() {
  gizmo.detach();
  requestDraw();  // the gizmo's matrices are updated by the draw (its picking needs them)
  const sel = S.selected;
  if (!sel) return;
  gizmoTarget.quaternion.identity();
  if (sel.type === 'pair') {  // the pair's target (or source): each drag is one move_pair
    const pt = S.state.points;
    gizmoTarget.position.fromArray((pairEnd() === 'source' ? pt.sources : pt.targets)[sel.index]);
    gizmo.setMode('translate');
    gizmo.attach(gizmoTarget);
    return;
  }
  if (sel.type === 'curve') {  // after a fit the moved point (the pose), before it the point
    const cv = S.state.curve, moving = S.state.fit && !S.state.stale;
    gizmoTarget.position.fromArray((moving ? cv.moved : cv.control)[sel.index]);
    gizmo.setMode('translate');
    gizmo.attach(gizmoTarget);
    return;
  }
  if (sel.type === 'pose') {
    gizmoTarget.position.fromArray(pivotOf(sel.handle));
    gizmo.setMode($('mode').value);
  } else {
    const s = findSelector(sel);
    if (!s || s.kind === 'other') return;
    gizmoTarget.position.fromArray(s.center);
    if (s.kind === 'plane') gizmoTarget.quaternion.setFromUnitVectors(new THREE.Vector3(0, 0, 1), new THREE.Vector3(...s.normal));
    gizmo.setMode(s.kind === 'plane' ? $('mode').value : 'translate');
  }
  gizmo.attach(gizmoTarget);
}

gizmo.addEventListener('dragging-changed', (e) => {
  orbit.enabled = !e.value;
  const sel = S.selected;
  if (e.value) {
    drag = { start: gizmoTarget.position.clone(), q0: gizmoTarget.quaternion.clone(),
      base: sel && sel.type === 'pose' ? S.poses[sel.handle].map((r) => r.slice()) : null };
    return;
  }
  if (!sel || !drag) return;
  if (sel.type === 'pair') {  // one request per drag: the server checks, refits, records
    act({ op: 'move_pair', index: sel.index, [pairEnd()]: gizmoTarget.position.toArray() })
      .then((st) => { S.pairDrag = null; return applyState(st); });
  } else if (sel.type === 'curve') {
    act({ op: 'move_curve_point', index: sel.index, center: gizmoTarget.position.toArray(),
      moved: !!(S.state.fit && !S.state.stale), commit: true }).then(applyState);
  } else if (sel.type === 'pose') {
    act({ op: 'pose', handle: sel.handle, matrix: S.poses[sel.handle], commit: true }).then(applyState);
  } else {
    const s = findSelector(sel);
    const req = { op: 'move_selector', role: s.role, index: s.index, handle: s.handle,
      center: gizmoTarget.position.toArray() };
    if (s.kind === 'plane') req.normal = new THREE.Vector3(0, 0, 1).applyQuaternion(gizmoTarget.quaternion).toArray();
    act(req).then(applyState);
  }
  drag = null;
});

let lastInput = 0;
renderer.domElement.addEventListener('pointermove', (e) => { lastInput = performance.now(); }, true);

gizmo.addEventListener('objectChange', () => {
  const sel = S.selected;
  if (!sel || !drag) { requestDraw(); return; }
  if (sel.type === 'pair') {  // the arrow follows the gizmo; the fit follows at the drag's end
    S.pairDrag = { index: sel.index, end: pairEnd(), at: gizmoTarget.position.toArray() };
    renderPairs();
    requestDraw();
  } else if (sel.type === 'curve') {
    const cv = S.state.curve, p = gizmoTarget.position.toArray();
    if (S.state.fit && !S.state.stale) {  // a pose step: new delta C, a draw, 1 point to the server
      cv.moved[sel.index] = p;
      computeDelta();
      renderCurve();
      pendingInput = lastInput || performance.now();
      draw();
      act({ op: 'move_curve_point', index: sel.index, center: p, moved: true }, true);
    } else {
      cv.control[sel.index] = p; cv.moved[sel.index] = p;
      renderCurve();
      requestDraw();
    }
  } else if (sel.type === 'pose') {
    // rotate about the drag's start point, then move: D = T(pos) R T(-start); pose = D base
    const q = gizmoTarget.quaternion.clone().multiply(drag.q0.clone().invert());
    const R = new THREE.Matrix4().makeRotationFromQuaternion(q);
    const D = new THREE.Matrix4().makeTranslation(gizmoTarget.position.x, gizmoTarget.position.y, gizmoTarget.position.z)
      .multiply(R).multiply(new THREE.Matrix4().makeTranslation(-drag.start.x, -drag.start.y, -drag.start.z));
    const B = new THREE.Matrix4();
    B.set(...drag.base.flat());
    const M = D.multiply(B).elements;  // column-major
    const rows = [0, 1, 2, 3].map((r) => [0, 1, 2, 3].map((c) => M[4 * c + r]));
    setPose(sel.handle, rows, true, lastInput || performance.now());
  } else {
    const line = outlines.children.find((o) => o.userData.role === sel.role && o.userData.handle === sel.handle && o.userData.index === sel.index);
    if (line) { line.position.copy(gizmoTarget.position); line.quaternion.copy(gizmoTarget.quaternion); }
    requestDraw();
  }
});

// A pose change: new delta C in the uniforms, a draw, and (not awaited) 16 numbers to the server.
function setPose(h, rows, send = true, inputTime) {
  S.poses[h] = rows;
  computeDelta();
  pendingInput = inputTime === undefined ? pendingInput : inputTime;
  draw();  // now, not at the next animation frame: pointermove is already frame-aligned
  if (send) act({ op: 'pose', handle: h, matrix: rows }, true);
}

// ---- picking and placing -----------------------------------------------------------------
// Every drawn point (P + B dC) in canvas pixels: calls visit(i, sx, sy, w) for those in front.
function forEachOnScreen(visit) {
  const rect = renderer.domElement.getBoundingClientRect();
  const p = deformedPositions(), n = S.scene.n;
  camera.updateMatrixWorld();
  const m = new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse).elements;
  for (let i = 0; i < n; i++) {
    const px = p[3 * i], py = p[3 * i + 1], pz = p[3 * i + 2];
    const w = m[3] * px + m[7] * py + m[11] * pz + m[15];
    if (w <= 0) continue;
    const sx = ((m[0] * px + m[4] * py + m[8] * pz + m[12]) / w * 0.5 + 0.5) * rect.width;
    const sy = (0.5 - (m[1] * px + m[5] * py + m[9] * pz + m[13]) / w * 0.5) * rect.height;
    visit(i, sx, sy, w);
  }
  return { rect, p };
}

// The nearest point drawn within 12 px of a click: its index and drawn position (local
// coordinates), or null.
function pickPoint(clientX, clientY) {
  const canvas = renderer.domElement.getBoundingClientRect();
  const x = clientX - canvas.left, y = clientY - canvas.top;
  let best = -1, bestZ = Infinity;
  const { p } = forEachOnScreen((i, sx, sy, w) => {
    if ((sx - x) ** 2 + (sy - y) ** 2 < 144 && w < bestZ) { bestZ = w; best = i; }
  });
  return best < 0 ? null : { index: best, at: [p[3 * best], p[3 * best + 1], p[3 * best + 2]] };
}
function pick(clientX, clientY) {
  const hit = pickPoint(clientX, clientY);
  return hit && hit.at;
}
window.sdPick = pick;

// The pair whose source or target dot is drawn within 8 px of a click (the nearest), or -1.
function pickPair(clientX, clientY) {
  const pt = S.state && S.state.points;
  if (!pt) return -1;
  let best = -1, bestD = 64;
  for (let i = 0; i < pt.n; i++) {
    for (const p of [pt.sources[i], pt.targets[i]]) {
      const [sx, sy] = window.sdScreenOf(p), d = (sx - clientX) ** 2 + (sy - clientY) ** 2;
      if (d < bestD) { bestD = d; best = i; }
    }
  }
  return best;
}

function selectPair(index) {
  S.selected = { type: 'pair', index };
  renderTree(); attachGizmo(); applyPairInfo();
}
function applyPairInfo() {
  const pt = S.state && S.state.points, on = !!(S.selected && S.selected.type === 'pair');
  $('pair-remove').disabled = !on;
  $('pairinfo').textContent = !pt ? 'no pairs: "add pair", then click a source on the model'
    : `${pt.n} pairs · select one in the tree or click its dot, drag it with the gizmo` +
      (on ? ` · pair ${S.selected.index} selected` : '');
}

let down = null;
renderer.domElement.addEventListener('pointerdown', (e) => { down = [e.clientX, e.clientY]; });
renderer.domElement.addEventListener('pointerup', async (e) => {
  if (!down || gizmo.dragging || S.tool || stroke) return;
  if (Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 4) return;
  if (!S.placing) {  // a click on a pair's dot selects that pair
    const i = pickPair(e.clientX, e.clientY);
    if (i >= 0) selectPair(i);
    return;
  }
  const hit = pickPoint(e.clientX, e.clientY);
  if (!hit) { $('status').textContent = 'no point under the cursor: click on the model'; return; }
  const at = hit.at;
  if (S.placing[0] === 'pair') {  // the source: the picked point where the model was (undeformed)
    S.placing = null;
    const P = S.arrays.positions, i = hit.index;
    const st = await act({ op: 'add_pair', source: [P[3 * i], P[3 * i + 1], P[3 * i + 2]] });
    if (!st.error && st.points) S.selected = { type: 'pair', index: st.points.n - 1 };
    await applyState(st);
    if (!st.error) $('status').textContent = (st.message ? `${st.message} · ` : '') + 'drag the new pair\'s target with the gizmo';
    return;
  }
  if (S.placing[0] === 'curve') {  // stays on: every click adds a control point until "done"
    await applyState(await act({ op: 'add_curve_point', center: at }));
    return;
  }
  const [role, kind] = S.placing;
  S.placing = null;
  const handle = role === 'handle' ? Number($('active-handle').value || 0) : 0;
  const st = await act({ op: 'add_selector', role, kind, handle, center: at });
  const mine = st.selectors.filter((s) => s.role === role && s.handle === handle);
  if (!st.error && mine.length) S.selected = { type: 'selector', role, handle, index: mine[mine.length - 1].index };
  await applyState(st);
});

// ---- screen selection: the points drawn inside a rectangle, a lasso or under a brush stroke
// become an indices selector of a region (what splat editors' users expect)
const BRUSH_PX = 20;
function pointsInRect(x0, y0, x1, y1) {
  const c = renderer.domElement.getBoundingClientRect(), out = [];
  const [lx, hx, ly, hy] = [Math.min(x0, x1) - c.left, Math.max(x0, x1) - c.left,
    Math.min(y0, y1) - c.top, Math.max(y0, y1) - c.top];
  forEachOnScreen((i, sx, sy) => { if (sx >= lx && sx <= hx && sy >= ly && sy <= hy) out.push(i); });
  return out;
}

function pointsInLasso(path) {  // even-odd rule against the closed polygon (page pixels)
  const c = renderer.domElement.getBoundingClientRect(), out = [];
  const poly = path.map(([x, y]) => [x - c.left, y - c.top]);
  forEachOnScreen((i, sx, sy) => {
    let inside = false;
    for (let a = 0, b = poly.length - 1; a < poly.length; b = a++) {
      const [xa, ya] = poly[a], [xb, yb] = poly[b];
      if ((ya > sy) !== (yb > sy) && sx < (xb - xa) * (sy - ya) / (yb - ya) + xa) inside = !inside;
    }
    if (inside) out.push(i);
  });
  return out;
}

function pointsUnderBrush(path, radius = BRUSH_PX) {
  const c = renderer.domElement.getBoundingClientRect(), out = [];
  const pts = path.map(([x, y]) => [x - c.left, y - c.top]);
  forEachOnScreen((i, sx, sy) => {
    if (pts.some(([x, y]) => (sx - x) ** 2 + (sy - y) ** 2 <= radius * radius)) out.push(i);
  });
  return out;
}

const overlay = document.createElement('canvas');
overlay.id = 'overlay';
document.body.appendChild(overlay);
function drawOverlay(path, shape) {
  overlay.width = window.innerWidth; overlay.height = window.innerHeight;
  const g = overlay.getContext('2d');
  g.clearRect(0, 0, overlay.width, overlay.height);
  if (!path) return;
  g.strokeStyle = '#ff781e'; g.fillStyle = 'rgba(255,120,30,0.25)'; g.setLineDash([4, 3]);
  const [x0, y0] = path[0], [x1, y1] = path[path.length - 1];
  if (shape === 'rect') { g.strokeRect(Math.min(x0, x1), Math.min(y0, y1), Math.abs(x1 - x0), Math.abs(y1 - y0)); return; }
  if (shape === 'brush') { for (const [x, y] of path) { g.beginPath(); g.arc(x, y, BRUSH_PX, 0, 2 * Math.PI); g.fill(); } return; }
  g.beginPath(); g.moveTo(x0, y0);
  for (const [x, y] of path) g.lineTo(x, y);
  g.closePath(); g.stroke();
}

let stroke = null;
renderer.domElement.addEventListener('pointerdown', (e) => {
  if (!S.tool) return;
  stroke = [[e.clientX, e.clientY]];
  orbit.enabled = false;
}, true);
renderer.domElement.addEventListener('pointermove', (e) => {
  if (!stroke) return;
  stroke.push([e.clientX, e.clientY]);
  drawOverlay(stroke, S.tool.shape);
});
renderer.domElement.addEventListener('pointerup', async (e) => {
  if (!stroke) return;
  stroke.push([e.clientX, e.clientY]);
  const path = stroke, { role, shape } = S.tool;
  stroke = null; S.tool = null; orbit.enabled = true;
  drawOverlay(null);
  const [x0, y0] = path[0], [x1, y1] = path[path.length - 1];
  const indices = shape === 'rect' ? pointsInRect(x0, y0, x1, y1)
    : shape === 'lasso' ? pointsInLasso(path) : pointsUnderBrush(path);
  const handle = role === 'handle' ? Number($('active-handle').value || 0) : 0;
  const st = await act({ op: 'add_indices', role, handle, indices });
  const mine = (st.selectors || []).filter((s) => s.role === role && s.handle === handle);
  if (!st.error && mine.length) S.selected = { type: 'selector', role, handle, index: mine[mine.length - 1].index };
  await applyState(st);
});
window.sdSelectIn = { rect: pointsInRect, lasso: pointsInLasso, brush: pointsUnderBrush };

// ---- panel -------------------------------------------------------------------------------
for (const b of document.querySelectorAll('[data-select]')) {
  b.onclick = () => {
    const shape = $('select-shape').value;
    S.tool = { role: b.dataset.select, shape }; S.placing = null;
    $('status').textContent = `drag a ${shape} on the view: its points join the ${b.dataset.select} region`;
  };
}
for (const b of document.querySelectorAll('[data-add]')) {
  b.onclick = () => { S.placing = b.dataset.add.split(' '); $('status').textContent = `click on the model to place the ${b.dataset.add}`; };
}
// a selector of any kind typed as YAML: added to a region, or replacing the selected one
for (const b of document.querySelectorAll('[data-text]')) {
  b.onclick = async () => {
    const role = b.dataset.text, handle = role === 'handle' ? Number($('active-handle').value || 0) : 0;
    const st = await act({ op: 'add_selector_text', role, handle, text: $('sel-text').value });
    const mine = (st.selectors || []).filter((s) => s.role === role && s.handle === handle);
    if (!st.error && mine.length) S.selected = { type: 'selector', role, handle, index: mine[mine.length - 1].index };
    await applyState(st);
  };
}
$('text-replace').onclick = async () => {
  const s = S.selected && S.selected.type === 'selector' ? findSelector(S.selected) : null;
  if (!s) { $('status').textContent = 'select a selector in the tree first'; return; }
  await applyState(await act({ op: 'set_selector_text', role: s.role, index: s.index, handle: s.handle,
    text: $('sel-text').value }));
};
$('curve-add').onclick = () => { S.placing = ['curve']; S.tool = null;
  $('status').textContent = 'click on the model: each click adds a control point (done ends)'; };
$('curve-done').onclick = () => { if (S.placing && S.placing[0] === 'curve') S.placing = null; $('status').textContent = ''; };
$('curve-reset').onclick = async () => applyState(await act({ op: 'reset_curve' }));
$('curve-remove').onclick = async () => { S.selected = null; applyState(await act({ op: 'remove_curve' })); };
$('curve-radius').onchange = async () => applyState(await act({ op: 'curve_settings', capture_radius: Number($('curve-radius').value) }));
$('curve-degree').onchange = async () => applyState(await act({ op: 'curve_settings', degree: Number($('curve-degree').value) }));
$('active-handle').onchange = () => { S.activeHandle = Number($('active-handle').value); };
$('remove-handle').onclick = async () => {
  const handle = Number($('active-handle').value || 0);
  if (S.selected && S.selected.type === 'pose') S.selected = null;
  applyState(await act({ op: 'remove_handle', handle }));
};
$('pair-add').onclick = () => { S.placing = ['pair']; S.tool = null;
  $('status').textContent = 'click on the model: the point becomes the new pair\'s source'; };
$('pair-remove').onclick = async () => {
  if (!(S.selected && S.selected.type === 'pair')) { $('status').textContent = 'select a pair first'; return; }
  const index = S.selected.index;
  S.selected = null;
  applyState(await act({ op: 'remove_pair', index }));
};
$('pair-end').onchange = attachGizmo;
$('new-handle').onclick = async () => { const st = await act({ op: 'add_handle' }); S.activeHandle = st.handles - 1; applyState(st); };
$('fit').onclick = async () => {
  $('fit').disabled = true; $('fitinfo').textContent = 'fitting …';
  const st = await act({ op: 'fit' });
  $('fit').disabled = false;
  S.selected = null;
  await applyState(st);
};
$('reset').onclick = async () => applyState(await act({ op: 'reset_pose', handle: S.selected && S.selected.type === 'pose' ? S.selected.handle : 0 }));
$('undo').onclick = async () => applyState(await act({ op: 'undo' }));
$('redo').onclick = async () => applyState(await act({ op: 'redo' }));
$('remove').onclick = async () => {
  if (S.selected && S.selected.type === 'pair') { $('pair-remove').click(); return; }
  if (S.selected && S.selected.type === 'pose') {  // a handle's row: the handle and its pose
    const handle = S.selected.handle;
    S.selected = null;
    applyState(await act({ op: 'remove_handle', handle }));
    return;
  }
  if (S.selected && S.selected.type === 'curve') {
    const index = S.selected.index;
    S.selected = null;
    applyState(await act({ op: 'remove_curve_point', index }));
    return;
  }
  const s = S.selected && S.selected.type === 'selector' ? findSelector(S.selected) : null;
  if (!s) return;
  S.selected = null;
  applyState(await act({ op: 'remove_selector', role: s.role, index: s.index, handle: s.handle }));
};
async function numericEdit() {
  const s = S.selected && S.selected.type === 'selector' ? findSelector(S.selected) : null;
  if (!s) return;
  const center = ['cx', 'cy', 'cz'].map((id) => Number($(id).value));
  let size = ['sx', 'sy', 'sz'].map((id) => Number($(id).value));
  if (s.kind === 'sphere') size = [size[0], size[0], size[0]];
  const req = { op: 'move_selector', role: s.role, index: s.index, handle: s.handle, center };
  if (s.kind !== 'plane') req.size = size;
  applyState(await act(req));
}
for (const id of ['cx', 'cy', 'cz', 'sx', 'sy', 'sz']) $(id).onchange = numericEdit;
$('mode').onchange = attachGizmo;
$('psize').oninput = () => requestDraw();
$('regions').onchange = () => { material.uniforms.u_show_regions.value = $('regions').checked ? 1 : 0; requestDraw(); };
$('up').onchange = () => setUp($('up').value);
$('covariance').onchange = async () => applyState(await act({ op: 'covariance', mode: $('covariance').value }));
// Saves go into the editor's save folder by file name; an existing file is only replaced
// after the user presses Replace for the same names (the server asks with `confirm`).
async function save(replace) {
  $('save').disabled = true;
  const st = await act({ op: 'save', model: $('out-model').value, yaml: $('out-yaml').value,
                         png: $('out-png').value, replace });
  $('save').disabled = false;
  $('replace').hidden = !st.confirm;
  window.sdLastSave = st;
  applyState(st);
}
$('save').onclick = () => save(false);
$('replace').onclick = () => save(true);
window.addEventListener('keydown', (e) => {
  if (!(e.ctrlKey || e.metaKey) || e.target.tagName === 'INPUT') return;
  if (e.key === 'z' && !e.shiftKey) { e.preventDefault(); $('undo').click(); }
  if (e.key === 'y' || (e.key === 'z' && e.shiftKey)) { e.preventDefault(); $('redo').click(); }
});
orbit.addEventListener('change', () => requestDraw());

const UPS = { '+x': [1, 0, 0], '-x': [-1, 0, 0], '+y': [0, 1, 0], '-y': [0, -1, 0], '+z': [0, 0, 1], '-z': [0, 0, -1] };
function setUp(name) {
  const up = new THREE.Vector3(...UPS[name]);
  camera.up.copy(up);
  const d = S.scene.diagonal;
  // a view from the front-right and a little above, in the frame whose y is `up`
  const side = Math.abs(up.y) > 0.5 ? new THREE.Vector3(0, 0, 1) : new THREE.Vector3(0, 1, 0);
  const right = new THREE.Vector3().crossVectors(up, side).normalize();
  const front = new THREE.Vector3().crossVectors(right, up).normalize();
  camera.position.copy(front.multiplyScalar(1.6 * d)).add(right.multiplyScalar(0.9 * d)).add(up.clone().multiplyScalar(0.6 * d));
  camera.near = d * 1e-3; camera.far = d * 50; camera.updateProjectionMatrix();
  orbit.target.set(0, 0, 0);
  orbit.update();
  requestDraw();
}

function background() {
  const c = S.arrays.colors;
  let sum = 0;
  const step = Math.max(1, Math.floor(S.scene.n / 5000));
  let cnt = 0;
  for (let i = 0; i < S.scene.n; i += step) { sum += 0.3 * c[4 * i] + 0.59 * c[4 * i + 1] + 0.11 * c[4 * i + 2]; cnt++; }
  return sum / cnt / 255 > 0.5 ? 0x23262b : 0xe9eaee;  // contrast with the model's colours
}

// ---- parity hook: the page's deform math read back by transform feedback ------------------
window.sdParity = (input) => {
  const { k, positions, normals, cov6, basis } = input;
  const n = positions.length / 3;
  const shape = input.shape || new Array(2 * n).fill(0);
  const g2 = document.createElement('canvas').getContext('webgl2');
  const vs = `#version 300 es\n${source({ K: k, COVARIANCE: covarianceDefine(input.mode || 'jacobian') },
    'deform.glsl', 'covariance.glsl', 'covariance_page.glsl', 'parity.vert')}`;
  const fs = '#version 300 es\nprecision highp float;\nout vec4 o;\nvoid main() { o = vec4(0.0); }';
  const prog = g2.createProgram();
  for (const [type, src] of [[g2.VERTEX_SHADER, vs], [g2.FRAGMENT_SHADER, fs]]) {
    const sh = g2.createShader(type); g2.shaderSource(sh, src); g2.compileShader(sh);
    if (!g2.getShaderParameter(sh, g2.COMPILE_STATUS)) throw new Error(g2.getShaderInfoLog(sh));
    g2.attachShader(prog, sh);
  }
  const outs = ['o_position', 'o_normal', 'o_cov_a', 'o_cov_b', 'o_r0', 'o_r1', 'o_r2'];
  g2.transformFeedbackVaryings(prog, outs, g2.INTERLEAVED_ATTRIBS);
  g2.linkProgram(prog);
  if (!g2.getProgramParameter(prog, g2.LINK_STATUS)) throw new Error(g2.getProgramInfoLog(prog));
  g2.useProgram(prog);
  const attr = (name, data, size = 3) => {
    const loc = g2.getAttribLocation(prog, name);
    if (loc < 0) return;
    const b = g2.createBuffer(); g2.bindBuffer(g2.ARRAY_BUFFER, b);
    g2.bufferData(g2.ARRAY_BUFFER, new Float32Array(data), g2.STATIC_DRAW);
    g2.enableVertexAttribArray(loc); g2.vertexAttribPointer(loc, size, g2.FLOAT, false, 0, 0);
  };
  const ca = [], cb = [];
  for (let i = 0; i < n; i++) { ca.push(cov6[6 * i], cov6[6 * i + 1], cov6[6 * i + 2]); cb.push(cov6[6 * i + 3], cov6[6 * i + 4], cov6[6 * i + 5]); }
  attr('position', positions); attr('normal', normals); attr('cov_a', ca); attr('cov_b', cb); attr('shape', shape, 2);
  const texels = n * k, width = Math.min(4096, texels), height = Math.ceil(texels / width);
  const data = new Float32Array(width * height * 4); data.set(basis);
  const tex = g2.createTexture(); g2.bindTexture(g2.TEXTURE_2D, tex);
  g2.texParameteri(g2.TEXTURE_2D, g2.TEXTURE_MIN_FILTER, g2.NEAREST);
  g2.texParameteri(g2.TEXTURE_2D, g2.TEXTURE_MAG_FILTER, g2.NEAREST);
  g2.texImage2D(g2.TEXTURE_2D, 0, g2.RGBA32F, width, height, 0, g2.RGBA, g2.FLOAT, data);
  g2.uniform1i(g2.getUniformLocation(prog, 'u_basis'), 0);
  g2.uniform1i(g2.getUniformLocation(prog, 'u_basis_width'), width);
  g2.uniform3fv(g2.getUniformLocation(prog, 'u_delta'), new Float32Array(input.delta));
  const outBuf = g2.createBuffer(); g2.bindBuffer(g2.TRANSFORM_FEEDBACK_BUFFER, outBuf);
  g2.bufferData(g2.TRANSFORM_FEEDBACK_BUFFER, n * 21 * 4, g2.STATIC_READ);
  g2.bindBufferBase(g2.TRANSFORM_FEEDBACK_BUFFER, 0, outBuf);
  g2.enable(g2.RASTERIZER_DISCARD);
  g2.beginTransformFeedback(g2.POINTS); g2.drawArrays(g2.POINTS, 0, n); g2.endTransformFeedback();
  const got = new Float32Array(n * 21);
  g2.getBufferSubData(g2.TRANSFORM_FEEDBACK_BUFFER, 0, got);
  return Array.from(got);
};
// delta C as the page computes it from poses (for the parity test of the per-pose path)
window.sdDelta = (poses, control) => { const keep = [S.poses, S.fit.control, S.fit.k];
  S.poses = poses; S.fit.control = control; S.fit.k = control.length;
  const d = []; for (let k = 0; k < control.length; k++) { const t = affine(poses[Math.floor(k / 4)], control[k]); for (let j = 0; j < 3; j++) d.push(t[j] - control[k][j]); }
  [S.poses, S.fit.control, S.fit.k] = keep; return d; };

// ---- start -------------------------------------------------------------------------------
async function start() {
  await loadShaders();
  S.scene = await api('/api/scene');
  $('title').textContent = `${S.scene.name} (${S.scene.kind}, ${S.scene.n.toLocaleString()} points; normals: ${S.scene.normals})`;
  await loadArrays();
  scene3.background = new THREE.Color(background());
  buildModel();
  resize();
  $('up').value = S.scene.up;
  $('covariance-row').hidden = S.scene.kind !== 'splats';
  $('covariance').value = S.scene.covariance;
  setUp(S.scene.up);
  const st = await api('/api/state');
  [$('out-model').value, $('out-yaml').value, $('out-png').value] = st.defaults;
  $('save-folder').textContent = `into ${st.save_folder} (file names only)`;
  await applyState(st);
  window.sdReady = true;
}
window.sdApply = applyState;
window.sdGizmo = gizmo;
window.sdDebug = { model: () => model, outlines, gizmo, order: () => S.order, curve: () => curveGroup, pairs: () => pairsGroup };
window.sdAct = async (req) => { const st = await act(req); await applyState(st); return st; };
window.sdState = () => S.shown;
window.sdSelect = (ref) => { S.selected = ref; renderTree(); attachGizmo(); applyPairInfo(); };
window.sdScreenOf = (p) => {  // page pixel of a local point (tests click on the model)
  const v = new THREE.Vector3(...p).project(camera), rect = renderer.domElement.getBoundingClientRect();
  return [rect.left + (v.x * 0.5 + 0.5) * rect.width, rect.top + (0.5 - v.y * 0.5) * rect.height];
};
window.sdGizmoScreen = () => {  // where the gizmo centre is on screen (for tests that drag it)
  const v = gizmoTarget.position.clone().project(camera), rect = renderer.domElement.getBoundingClientRect();
  return [rect.left + (v.x * 0.5 + 0.5) * rect.width, rect.top + (0.5 - v.y * 0.5) * rect.height];
};
start().catch((e) => { $('status').textContent = `page: ${e.message}`; window.sdError = String(e.stack || e); });
