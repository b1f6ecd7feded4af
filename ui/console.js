// The scone console: maps, one map in 3D with localisation, and a pair page. Everything it shows comes from
// the HTTP API of the server that serves it, with the key typed in the header (kept for the tab only).
import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";

const view = document.getElementById("view");
const statusLine = document.getElementById("status");
const keyInput = document.getElementById("api-key");
keyInput.value = sessionStorage.getItem("scone-key") || "";
keyInput.addEventListener("change", () => {
  sessionStorage.setItem("scone-key", keyInput.value);
  route();
});

function setStatus(text, error = false) {
  statusLine.textContent = text;
  statusLine.className = error ? "error" : "";
}

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "text") e.textContent = v;
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

/** fetch with the API key; a non-2xx answer throws with the server's error code and message. */
async function api(path, options = {}) {
  const headers = { ...(options.headers || {}) };
  if (keyInput.value) headers["x-api-key"] = keyInput.value;
  const r = await fetch(path, { ...options, headers });
  if (!r.ok) {
    let message = `${r.status} ${r.statusText}`;
    try {
      const j = await r.json();
      message = `${j.error.code}: ${j.error.message}`;
    } catch (_) { /* not the JSON envelope */ }
    throw new Error(message);
  }
  return r;
}

const fmt = (n) => Number(n).toLocaleString("en");

// ------------------------------------------------------------------------------------------------------
// Maps
// ------------------------------------------------------------------------------------------------------

async function mapsPage() {
  const list = await (await api("/v1/maps")).json();
  const table = el("table", { id: "maps-table" },
    el("thead", {}, el("tr", {},
      el("th", { text: "map" }), el("th", { class: "num", text: "keyframes" }),
      el("th", { class: "num", text: "landmarks" }), el("th", { class: "num", text: "observations" }),
      el("th", { class: "num", text: "version" }), el("th", { text: "index" }), el("th", { text: "model" }))));
  const body = el("tbody");
  for (const m of list.maps) {
    body.append(el("tr", { "data-map": m.map_id },
      el("td", {}, el("a", { href: `#/map/${encodeURIComponent(m.map_id)}`, text: m.map_id })),
      el("td", { class: "num", text: fmt(m.keyframes) }), el("td", { class: "num", text: fmt(m.landmarks) }),
      el("td", { class: "num", text: fmt(m.observations) }), el("td", { class: "num", text: fmt(m.version) }),
      el("td", { text: m.approximate_index ? "HNSW" : "exact" }), el("td", { class: "muted", text: m.model_id })));
  }
  table.append(body);
  const parts = [el("h2", { text: `Maps (${list.maps.length})` }), table];
  if (list.maps.length === 0) parts.push(el("p", { class: "muted", text: "No maps yet: create one through the API." }));
  for (const h of list.held_back) {
    parts.push(el("p", { class: "error", text: `held back: ${h.map_id}: ${h.reason}` }));
  }
  view.replaceChildren(...parts);
  setStatus(`${list.maps.length} maps`);
}

// ------------------------------------------------------------------------------------------------------
// One map in 3D
// ------------------------------------------------------------------------------------------------------

let stopRendering = () => {};

/** Camera-to-world pose as a THREE.Matrix4 (OpenCV camera axes, as stored). */
function poseMatrix(p) {
  const m = new THREE.Matrix4();
  m.compose(new THREE.Vector3(p.tx, p.ty, p.tz), new THREE.Quaternion(p.qx, p.qy, p.qz, p.qw), new THREE.Vector3(1, 1, 1));
  return m;
}

/** Line segments of a camera frustum of depth `d` for intrinsics `k`, in world coordinates. */
function frustumSegments(pose, k, d) {
  const m = poseMatrix(pose);
  const w = k.width || 2 * k.cx, h = k.height || 2 * k.cy;
  const corner = (u, v) => new THREE.Vector3(((u - k.cx) / k.fx) * d, ((v - k.cy) / k.fy) * d, d).applyMatrix4(m);
  const o = new THREE.Vector3(0, 0, 0).applyMatrix4(m);
  const c = [corner(0, 0), corner(w, 0), corner(w, h), corner(0, h)];
  const pts = [];
  for (let i = 0; i < 4; i++) pts.push(o, c[i], c[i], c[(i + 1) % 4]);
  return pts;
}

function frustaObject(views, depth, colour) {
  const pts = [];
  for (const v of views) pts.push(...frustumSegments(v.pose, v.intrinsics, depth));
  const g = new THREE.BufferGeometry().setFromPoints(pts);
  return new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: colour }));
}

function buildScene(canvas, contents) {
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x0b0d10);

  const n = contents.landmarks.length;
  const positions = new Float32Array(n * 3);
  const colours = new Float32Array(n * 3);
  contents.landmarks.forEach((l, i) => positions.set([l.x, l.y, l.z], i * 3));
  // The view frames the bulk of the map: the median point as centre, and the distance that holds 90 % of the
  // landmarks and cameras as its size (a few far, badly triangulated points must not shrink the map to a dot).
  const points = contents.landmarks.map((l) => new THREE.Vector3(l.x, l.y, l.z))
    .concat(contents.keyframes.map((k) => new THREE.Vector3(k.pose.tx, k.pose.ty, k.pose.tz)));
  const median = (values) => {
    const v = [...values].sort((a, b) => a - b);
    return v.length ? v[Math.floor(v.length / 2)] : 0;
  };
  const centre = new THREE.Vector3(median(points.map((p) => p.x)), median(points.map((p) => p.y)), median(points.map((p) => p.z)));
  const distances = points.map((p) => p.distanceTo(centre)).sort((a, b) => a - b);
  const extent = Math.max(2 * (distances.length ? distances[Math.floor(0.9 * (distances.length - 1))] : 1), 1e-3);

  // The cameras' mean "up" (OpenCV's -y) and viewing direction set the initial view.
  const up = new THREE.Vector3(), forward = new THREE.Vector3();
  for (const k of contents.keyframes) {
    const q = new THREE.Quaternion(k.pose.qx, k.pose.qy, k.pose.qz, k.pose.qw);
    up.add(new THREE.Vector3(0, -1, 0).applyQuaternion(q));
    forward.add(new THREE.Vector3(0, 0, 1).applyQuaternion(q));
  }
  if (up.lengthSq() < 1e-9) up.set(0, 1, 0);
  if (forward.lengthSq() < 1e-9) forward.set(0, 0, -1);
  up.normalize();
  forward.normalize();

  // Landmarks coloured by height along "up", blue (low) to orange (high).
  const heights = contents.landmarks.map((l) => new THREE.Vector3(l.x, l.y, l.z).sub(centre).dot(up));
  const sorted = [...heights].sort((a, b) => a - b);
  const lo = sorted.length ? sorted[Math.floor(0.05 * (sorted.length - 1))] : 0;
  const hi = sorted.length ? sorted[Math.floor(0.95 * (sorted.length - 1))] : 1;
  const c = new THREE.Color();
  heights.forEach((h, i) => {
    c.setHSL(0.6 - 0.55 * Math.min(1, Math.max(0, (h - lo) / (hi - lo || 1))), 0.85, 0.55);
    colours.set([c.r, c.g, c.b], i * 3);
  });
  const g = new THREE.BufferGeometry();
  g.setAttribute("position", new THREE.BufferAttribute(positions, 3));
  g.setAttribute("color", new THREE.BufferAttribute(colours, 3));
  scene.add(new THREE.Points(g, new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true })));
  const frustumDepth = extent * 0.04;
  scene.add(frustaObject(contents.keyframes, frustumDepth, 0x9aa4b2));

  const camera = new THREE.PerspectiveCamera(55, 1, extent * 1e-3, extent * 100);
  camera.up.copy(up);
  // From behind and above the mapping cameras, looking at the map: frusta in front, the scene beyond them.
  const cameras = new THREE.Vector3();
  for (const k of contents.keyframes) cameras.add(new THREE.Vector3(k.pose.tx, k.pose.ty, k.pose.tz));
  if (contents.keyframes.length) cameras.divideScalar(contents.keyframes.length);
  else cameras.copy(centre).addScaledVector(forward, -0.5 * extent);
  camera.position.copy(cameras).addScaledVector(forward, -0.5 * extent).addScaledVector(up, 0.35 * extent);
  const controls = new OrbitControls(camera, canvas);
  controls.target.copy(centre);
  controls.update();

  let estimate = null;
  let running = true;
  const state = { frames: 0, landmarks: n, keyframes: contents.keyframes.length, estimate: null };
  window.sconeView = state;
  function frame() {
    if (!running) return;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.floor(w * renderer.getPixelRatio()) || canvas.height !== Math.floor(h * renderer.getPixelRatio())) {
      renderer.setSize(w, h, false);
      camera.aspect = w / Math.max(h, 1);
      camera.updateProjectionMatrix();
    }
    controls.update();
    renderer.render(scene, camera);
    state.frames += 1;
    requestAnimationFrame(frame);
  }
  requestAnimationFrame(frame);
  stopRendering = () => {
    running = false;
    controls.dispose();
    renderer.dispose();
  };
  return {
    /** Places the localised camera (red) in the view. */
    showEstimate(pose, intrinsics) {
      this.showEstimates([{ pose, intrinsics }]);
    },
    /** Places several localised cameras (a track's frames) in the view, replacing the last estimate. */
    showEstimates(views) {
      if (estimate) scene.remove(estimate);
      estimate = frustaObject(views, frustumDepth * 2, 0xff4d4d);
      scene.add(estimate);
      state.estimate = views.map((v) => v.pose);
    },
  };
}

function numberField(id, label, value) {
  return el("label", {}, `${label} `, el("input", { id, type: "number", step: "any", value: String(value) }));
}

async function mapPage(id) {
  const enc = encodeURIComponent(id);
  const [info, contents] = await Promise.all([
    api(`/v1/maps/${enc}`).then((r) => r.json()),
    api(`/v1/maps/${enc}/contents?max_landmarks=50000`).then((r) => r.json()),
  ]);
  const canvas = el("canvas", { id: "scene" });
  const k0 = contents.keyframes.length ? contents.keyframes[0].intrinsics : { fx: 525, fy: 525, cx: 319.5, cy: 239.5 };
  const stats = el("dl", {},
    el("dt", { text: "keyframes" }), el("dd", { text: fmt(info.keyframes) }),
    el("dt", { text: "landmarks" }), el("dd", { text: `${fmt(info.landmarks)} (${fmt(contents.landmarks.length)} drawn)` }),
    el("dt", { text: "observations" }), el("dd", { text: fmt(info.observations) }),
    el("dt", { text: "version" }), el("dd", { text: fmt(info.version) }),
    el("dt", { text: "index" }), el("dd", { text: info.approximate_index ? "HNSW" : "exact" }),
    el("dt", { text: "model" }), el("dd", { class: "muted", text: info.model_id }));
  const button = el("button", { id: "loc-go", text: "Localize" });
  const result = el("div", { id: "loc-result" });
  const form = el("div", { class: "panel" }, el("h2", { text: "Localize an image" }),
    el("div", { class: "form-row" }, el("input", { id: "loc-image", type: "file", accept: "image/png,image/jpeg" })),
    el("div", { class: "form-row" }, numberField("loc-fx", "fx", k0.fx), numberField("loc-fy", "fy", k0.fy)),
    el("div", { class: "form-row" }, numberField("loc-cx", "cx", k0.cx), numberField("loc-cy", "cy", k0.cy)),
    el("div", { class: "form-row" }, button), result);
  view.replaceChildren(
    el("h2", {}, el("a", { href: "#/", text: "Maps" }), ` / ${id}`),
    el("div", { class: "map-layout" },
      el("div", {}, canvas, el("p", { class: "muted", text: "Landmarks coloured by height; keyframes grey, the localised camera red. Drag to orbit, scroll to zoom." })),
      el("div", {}, el("div", { class: "panel" }, el("h2", { text: "Map" }), stats), form, trackPanel(enc, k0, () => scene3d))));
  const scene3d = buildScene(canvas, contents);
  setStatus(`map ${id}: ${fmt(contents.keyframes.length)} keyframes, ${fmt(contents.landmarks.length)} landmarks drawn`);

  button.addEventListener("click", async () => {
    const file = document.getElementById("loc-image").files[0];
    if (!file) {
      setStatus("choose an image first", true);
      return;
    }
    const intr = ["fx", "fy", "cx", "cy"].map((k) => `${k}=${encodeURIComponent(document.getElementById(`loc-${k}`).value)}`).join("&");
    const type = file.type || "application/octet-stream";
    button.disabled = true;
    setStatus("localising…");
    try {
      const body = await file.arrayBuffer();
      const url = `/v1/maps/${enc}/localize?${intr}`;
      const answer = await (await api(url, { method: "POST", headers: { "content-type": type }, body })).json();
      const pose = el("pre", { id: "loc-pose", text: JSON.stringify(answer, null, 2) });
      result.replaceChildren(
        el("p", { id: "loc-summary", "data-localized": String(answer.localized),
          text: answer.localized ? `localised: ${answer.inliers} inliers of ${answer.matches} matches` : `not localised (${answer.matches} matches)` }),
        pose);
      // The picture is a second call (the same work again); if it fails, the pose stays shown.
      try {
        const picture = await (await api(`${url}&render=png`, { method: "POST", headers: { "content-type": type }, body })).blob();
        result.append(el("img", { id: "loc-picture", class: "picture", alt: "inlier 2D-3D matches", src: URL.createObjectURL(picture) }));
      } catch (e) {
        result.append(el("p", { class: "error", text: `no picture: ${e.message || e}` }));
      }
      if (answer.localized) {
        const fx = Number(document.getElementById("loc-fx").value), fy = Number(document.getElementById("loc-fy").value);
        const cx = Number(document.getElementById("loc-cx").value), cy = Number(document.getElementById("loc-cy").value);
        scene3d.showEstimate(answer.pose, { fx, fy, cx, cy });
      }
      setStatus(answer.localized ? "localised" : "not localised");
    } catch (e) {
      setStatus(String(e.message || e), true);
    } finally {
      button.disabled = false;
    }
  });
}

/**
 * A tracker's poses from a file: a JSON array of poses ({tx, ty, tz, qx, qy, qz, qw}, camera-to-track), or
 * lines of 7 numbers (tx ty tz qx qy qz qw) or 8 (a timestamp first, the TUM trajectory format); '#' starts a
 * comment. Throws, naming the line, on anything else.
 */
function parsePoses(text) {
  const keys = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"];
  const trimmed = text.trim();
  if (trimmed.startsWith("[")) {
    const poses = JSON.parse(trimmed);
    poses.forEach((p, i) => {
      if (!keys.every((k) => Number.isFinite(p[k]))) throw new Error(`pose ${i}: needs finite ${keys.join(", ")}`);
    });
    return poses.map((p) => Object.fromEntries(keys.map((k) => [k, p[k]])));
  }
  const poses = [];
  text.split("\n").forEach((line, i) => {
    const body = line.split("#")[0].trim();
    if (!body) return;
    const numbers = body.split(/[\s,]+/).map(Number);
    if (!(numbers.length === 7 || numbers.length === 8) || !numbers.every(Number.isFinite)) {
      throw new Error(`poses file, line ${i + 1}: expected 7 numbers (tx ty tz qx qy qz qw) or 8 (a timestamp first)`);
    }
    const v = numbers.slice(numbers.length - 7);
    poses.push(Object.fromEntries(keys.map((k, j) => [k, v[j]])));
  });
  return poses;
}

/** The panel that localises a track: 2-10 images (in file-name order) and their poses in the tracker's frame. */
function trackPanel(enc, k0, scene3d) {
  const button = el("button", { id: "track-go", text: "Localize track" });
  const result = el("div", { id: "track-result" });
  button.addEventListener("click", async () => {
    const files = [...document.getElementById("track-images").files].sort((a, b) => a.name.localeCompare(b.name));
    const posesFile = document.getElementById("track-poses").files[0];
    if (files.length < 2 || files.length > 10 || !posesFile) {
      setStatus("choose 2-10 images and their poses file first", true);
      return;
    }
    button.disabled = true;
    setStatus("localising the track…");
    try {
      const poses = parsePoses(await posesFile.text());
      if (poses.length !== files.length) throw new Error(`${files.length} images but ${poses.length} poses in ${posesFile.name}`);
      const intrinsics = Object.fromEntries(["fx", "fy", "cx", "cy"].map((k) => [k, Number(document.getElementById(`track-${k}`).value)]));
      const request = {
        frames: poses.map((pose) => ({ frame: { intrinsics }, pose })),
        estimate_scale: document.getElementById("track-scale").checked,
      };
      const form = new FormData();
      form.append("request", JSON.stringify(request));
      files.forEach((f, i) => form.append(`track${i}`, f));
      const answer = await (await api(`/v1/maps/${enc}/localize-track`, { method: "POST", body: form })).json();
      const rows = answer.frames.map((f, i) => el("tr", { "data-frame": String(i) },
        el("td", { text: files[i].name }), el("td", { class: "num", text: `${f.inliers} / ${f.matches}` }),
        el("td", { text: f.dropped ? "dropped" : f.pose ? "localised" : "-" }),
        el("td", { text: f.localized_alone ? "yes" : "no" })));
      result.replaceChildren(
        el("p", { id: "track-summary", "data-localized": String(answer.localized),
          text: answer.localized ? `localised: ${answer.inliers} inliers over ${answer.frames.length} frames${answer.single_frame != null ? ` (frame ${answer.single_frame}'s pose alone)` : ""}` : "not localised" }),
        el("table", { id: "track-frames" }, el("thead", {}, el("tr", {}, el("th", { text: "image" }),
          el("th", { class: "num", text: "inliers / matches" }), el("th", { text: "in the estimate" }), el("th", { text: "alone" }))),
          el("tbody", {}, ...rows)),
        el("pre", { id: "track-answer", text: JSON.stringify(answer, null, 2) }));
      if (answer.localized) {
        scene3d().showEstimates(answer.frames.filter((f) => f.pose).map((f) => ({ pose: f.pose, intrinsics })));
      }
      setStatus(answer.localized ? "track localised" : "track not localised");
    } catch (e) {
      setStatus(String(e.message || e), true);
    } finally {
      button.disabled = false;
    }
  });
  return el("div", { class: "panel" }, el("h2", { text: "Localize a track" }),
    el("p", { class: "muted", text: "2-10 images (taken in file-name order) and a file of their poses in the tracker's frame: a JSON array of {tx, ty, tz, qx, qy, qz, qw}, or one line per image of 7 numbers, or 8 with a timestamp first (TUM)." }),
    el("div", { class: "form-row" }, el("label", { text: "images" }), el("input", { id: "track-images", type: "file", multiple: "", accept: "image/png,image/jpeg" })),
    el("div", { class: "form-row" }, el("label", { text: "poses" }), el("input", { id: "track-poses", type: "file", accept: ".txt,.json,text/plain,application/json" })),
    el("div", { class: "form-row" }, numberField("track-fx", "fx", k0.fx), numberField("track-fy", "fy", k0.fy)),
    el("div", { class: "form-row" }, numberField("track-cx", "cx", k0.cx), numberField("track-cy", "cy", k0.cy)),
    el("div", { class: "form-row" }, el("label", {}, el("input", { id: "track-scale", type: "checkbox" }), " estimate the scale (track units are not the map's)")),
    el("div", { class: "form-row" }, button), result);
}

// ------------------------------------------------------------------------------------------------------
// A pair: SConE and FREAK side by side
// ------------------------------------------------------------------------------------------------------

function pairPage() {
  const button = el("button", { id: "pair-go", text: "Match" });
  const results = el("div", { class: "pair-results", id: "pair-results" });
  view.replaceChildren(
    el("h2", { text: "Match two images" }),
    el("p", { class: "muted", text: "The same FAST keypoints matched by SConE (the service's default matcher) and by FREAK alone; inliers of the relative pose in green, outliers in red." }),
    el("div", { class: "form-row" }, el("label", { text: "image 1" }), el("input", { id: "pair-a", type: "file", accept: "image/png,image/jpeg" })),
    el("div", { class: "form-row" }, el("label", { text: "image 2" }), el("input", { id: "pair-b", type: "file", accept: "image/png,image/jpeg" })),
    el("div", { class: "form-row" }, numberField("pair-fx", "fx", 525), numberField("pair-fy", "fy", 525),
      numberField("pair-cx", "cx", 319.5), numberField("pair-cy", "cy", 239.5)),
    el("div", { class: "form-row" }, button), results);
  setStatus("choose two images");
  button.addEventListener("click", async () => {
    const a = document.getElementById("pair-a").files[0], b = document.getElementById("pair-b").files[0];
    if (!a || !b) {
      setStatus("choose two images first", true);
      return;
    }
    const intrinsics = Object.fromEntries(["fx", "fy", "cx", "cy"].map((k) => [k, Number(document.getElementById(`pair-${k}`).value)]));
    button.disabled = true;
    setStatus("matching…");
    try {
      const columns = [];
      // SConE with the model's own matcher (the request names none), beside FREAK on the same keypoints.
      for (const [matcher, title] of [["default", "SConE"], ["freak", "FREAK"]]) {
        const form = new FormData();
        const request = { frame1: { intrinsics }, frame2: { intrinsics } };
        if (matcher !== "default") request.matcher = matcher;
        form.append("request", JSON.stringify(request));
        form.append("image1", a);
        form.append("image2", b);
        const r = await api("/v1/match?render=png", { method: "POST", body: form });
        const matches = r.headers.get("x-scone-matches"), inliers = r.headers.get("x-scone-inliers");
        const picture = await r.blob();
        columns.push(el("div", { class: "panel", "data-matcher": matcher },
          el("h2", { text: `${title}: ${inliers} inliers of ${matches} matches` }),
          el("img", { class: "picture", alt: `${title} matches`, src: URL.createObjectURL(picture) })));
      }
      results.replaceChildren(...columns);
      setStatus("matched");
    } catch (e) {
      setStatus(String(e.message || e), true);
    } finally {
      button.disabled = false;
    }
  });
}

// ------------------------------------------------------------------------------------------------------

async function route() {
  stopRendering();
  stopRendering = () => {};
  const hash = location.hash || "#/";
  for (const [id, active] of [["nav-maps", !hash.startsWith("#/pair")], ["nav-pair", hash.startsWith("#/pair")]]) {
    document.getElementById(id).classList.toggle("active", active);
  }
  try {
    if (hash.startsWith("#/map/")) await mapPage(decodeURIComponent(hash.slice("#/map/".length)));
    else if (hash.startsWith("#/pair")) pairPage();
    else await mapsPage();
  } catch (e) {
    view.replaceChildren(el("p", { class: "error", id: "page-error", text: String(e.message || e) }));
    setStatus(String(e.message || e), true);
  }
}

window.addEventListener("hashchange", route);
route();
