// The 3D viewer of report.html (a classic script; needs the global THREE of the inlined
// three.js bundle). Reads the scene JSON written by postproc/pipeline/viewer.py: world
// frame W, z up, metres. The scene is drawn relative to its bounding-box minimum (float32
// precision on the GPU); every number shown is in W.
//
// URL hash options (also what the tests use): #hide=mesh,points,targets,keyframes,
// session:NAME (layers off at load), view=top|side|oblique, zoom=F (closer by F),
// colour=coverage (the mesh coloured by the coverage score).
// window.wreckmapViewer exposes ready, frames, toScreen(worldXYZ) and lastMeasure_m.
(function () {
  "use strict";
  const sceneDoc = JSON.parse(document.getElementById("wm-scene").textContent);
  const container = document.getElementById("wm-viewer");
  const canvas = document.getElementById("wm-canvas");
  const panel = document.getElementById("wm-panel");
  const labels = document.getElementById("wm-labels");
  const api = { ready: false, frames: 0, lastMeasure_m: null, error: null };
  window.wreckmapViewer = api;

  const hash = new URLSearchParams(window.location.hash.replace(/^#/, ""));
  // Without a hide= option the fused points start hidden when there is a mesh (they
  // would cover it); hide= (even empty) says exactly which layers start off.
  const hideOption = hash.get("hide");
  const hidden = new Set(
    hideOption === null
      ? (sceneDoc.mesh && sceneDoc.points ? ["points"] : [])
      : hideOption.split(",").filter((s) => s)
  );
  const origin = new THREE.Vector3().fromArray(sceneDoc.min_m);
  const step = sceneDoc.step_m;

  function bytes(b64) {
    const text = atob(b64);
    const out = new Uint8Array(text.length);
    for (let i = 0; i < text.length; i++) out[i] = text.charCodeAt(i);
    return out;
  }
  // uint16 triples -> float32 positions relative to the scene minimum (m).
  function positions(block) {
    const q = new Uint16Array(bytes(block.data).buffer);
    const p = new Float32Array(q.length);
    for (let i = 0; i < q.length; i += 3) {
      p[i] = q[i] * step[0];
      p[i + 1] = q[i + 1] * step[1];
      p[i + 2] = q[i + 2] * step[2];
    }
    return p;
  }
  // PLY colours are sRGB bytes; three.js lights and blends in linear RGB.
  const srgbToLinear = new Float32Array(256);
  for (let i = 0; i < 256; i++) {
    const c = i / 255;
    srgbToLinear[i] = c <= 0.04045 ? c / 12.92 : Math.pow((c + 0.055) / 1.055, 2.4);
  }
  function colours(b64) {
    const c = bytes(b64);
    const out = new Float32Array(c.length);
    for (let i = 0; i < c.length; i++) out[i] = srgbToLinear[c[i]];
    return new THREE.BufferAttribute(out, 3);
  }
  function local(xyz) {
    return new THREE.Vector3(xyz[0], xyz[1], xyz[2]).sub(origin);
  }

  let renderer;
  try {
    renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  } catch (error) {
    api.error = "WebGL not available: " + error;
    panel.textContent = api.error;
    return;
  }
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setClearColor(0x1d2630);
  const scene = new THREE.Scene();
  const camera = new THREE.PerspectiveCamera(45, 1, 0.01, 1000);
  camera.up.set(0, 0, 1);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x303840, 1.0));
  const sun = new THREE.DirectionalLight(0xffffff, 2.0);
  sun.position.set(0.3, -0.4, 1.0);
  scene.add(sun);

  const layers = {}; // name -> {objects: [], label, checked}
  function addLayer(name, label, objects, swatch) {
    layers[name] = { objects, label, swatch };
    objects.forEach((o) => scene.add(o));
  }

  const bounds = new THREE.Box3();
  let meshObject = null;
  let coverageColours = null; // per-vertex coverage colours, and the photo colours
  let photoColours = null;
  let pointsObject = null;
  const info = [];
  if (sceneDoc.mesh) {
    const m = sceneDoc.mesh;
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(positions(m.positions), 3));
    if (m.colours) {
      geometry.setAttribute("color", colours(m.colours));
    }
    geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(bytes(m.faces).buffer), 1));
    geometry.computeVertexNormals();
    geometry.computeBoundingBox();
    bounds.union(geometry.boundingBox);
    const material = new THREE.MeshLambertMaterial({
      vertexColors: !!m.colours, color: m.colours ? 0xffffff : 0xb0b0b0, side: THREE.DoubleSide,
    });
    meshObject = new THREE.Mesh(geometry, material);
    addLayer("mesh", "mesh", [meshObject]);
    if (m.coverage) {
      // The coverage score per vertex on the red-yellow-green ramp of the coverage maps.
      const ramp = [[215, 48, 39], [254, 224, 139], [26, 152, 80]];
      const score = bytes(m.coverage);
      const out = new Float32Array(score.length * 3);
      for (let i = 0; i < score.length; i++) {
        const t = score[i] / 255 * 2, k = Math.min(Math.floor(t), 1), f = t - k;
        for (let j = 0; j < 3; j++) {
          out[3 * i + j] = srgbToLinear[Math.round(ramp[k][j] * (1 - f) + ramp[k + 1][j] * f)];
        }
      }
      coverageColours = new THREE.BufferAttribute(out, 3);
      photoColours = geometry.getAttribute("color") || null;
    }
    info.push(
      m.triangles === m.full_triangles
        ? `mesh: ${m.triangles.toLocaleString()} triangles (${m.file}, in full)`
        : `mesh: ${m.triangles.toLocaleString()} of ${m.full_triangles.toLocaleString()} ` +
          `triangles (vertex clustering, ${(m.cell_m * 100).toFixed(1)} cm cells; full mesh: ${m.file})`
    );
  }
  if (sceneDoc.points) {
    const pts = sceneDoc.points;
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(positions(pts.positions), 3));
    if (pts.colours) {
      geometry.setAttribute("color", colours(pts.colours));
    }
    geometry.computeBoundingBox();
    // Framing follows the mesh when there is one (fused points carry far outliers).
    if (!sceneDoc.mesh) bounds.union(geometry.boundingBox);
    pointsObject = new THREE.Points(
      geometry,
      new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: !!pts.colours,
                                 color: pts.colours ? 0xffffff : 0xdddddd })
    );
    addLayer("points", "fused points", [pointsObject]);
    const n = pts.positions.count;
    info.push(
      n === pts.full_count
        ? `points: ${n.toLocaleString()} (${pts.file})`
        : `points: ${n.toLocaleString()} of ${pts.full_count.toLocaleString()} (random; full: ${pts.file})`
    );
  }
  for (const t of sceneDoc.targets) {
    const pose = new THREE.Matrix4().fromArray(t.pose).transpose();
    for (const c of [[0, 0, 0], [t.extent_m[0], t.extent_m[1], 0]]) {
      bounds.expandByPoint(local(new THREE.Vector3(...c).applyMatrix4(pose).toArray()));
    }
  }
  const allCameras = [];
  for (const s of sceneDoc.sessions) {
    for (const p of s.poses) {
      const v = local([p[3], p[7], p[11]]);
      bounds.expandByPoint(v);
      allCameras.push(v);
    }
  }
  if (bounds.isEmpty()) bounds.expandByPoint(new THREE.Vector3(0, 0, 0));
  const size = bounds.getSize(new THREE.Vector3());
  const radius = Math.max(size.length() / 2, 0.5);
  const centre = bounds.getCenter(new THREE.Vector3());
  // Glyph size for cameras and markers: a small fraction of the scene.
  const glyph = Math.max(radius / 90, 0.01);

  for (const s of sceneDoc.sessions) {
    const colour = new THREE.Color(s.colour);
    const path = s.poses.map((p) => local([p[3], p[7], p[11]]));
    const line = new THREE.Line(
      new THREE.BufferGeometry().setFromPoints(path),
      new THREE.LineBasicMaterial({ color: colour })
    );
    // A frustum per keyframe: apex at the centre, a rectangle 1 glyph ahead (camera z).
    const corners = [[-0.8, -0.5, 1.0], [0.8, -0.5, 1.0], [0.8, 0.5, 1.0], [-0.8, 0.5, 1.0]];
    const seg = [];
    for (const p of s.poses) {
      const pose = new THREE.Matrix4().fromArray(p).transpose();
      const apex = new THREE.Vector3(0, 0, 0).applyMatrix4(pose);
      const cs = corners.map((c) =>
        new THREE.Vector3(c[0] * glyph, c[1] * glyph, c[2] * glyph).applyMatrix4(pose));
      for (let i = 0; i < 4; i++) {
        seg.push(apex, cs[i], cs[i], cs[(i + 1) % 4]);
      }
    }
    const frusta = new THREE.LineSegments(
      new THREE.BufferGeometry().setFromPoints(seg.map((v) => v.clone().sub(origin))),
      new THREE.LineBasicMaterial({ color: colour, transparent: true, opacity: 0.7 })
    );
    frusta.userData.keyframes = true;
    addLayer("session:" + s.name, `${s.name} (${s.poses.length} keyframes)`, [line, frusta], s.colour);
    if (!s.in_world) info.push(`${s.name}: keyframes in its own SLAM frame (${s.source})`);
  }
  const targetLabels = [];
  if (sceneDoc.targets.length) {
    const objects = [];
    for (const t of sceneDoc.targets) {
      const pose = new THREE.Matrix4().fromArray(t.pose).transpose();
      const [w, h] = t.extent_m;
      const outline = [[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]].map((c) =>
        new THREE.Vector3(...c).applyMatrix4(pose).sub(origin));
      const board = new THREE.Mesh(
        new THREE.BufferGeometry().setFromPoints([outline[0], outline[1], outline[2],
                                                  outline[0], outline[2], outline[3]]),
        new THREE.MeshBasicMaterial({ color: 0xffe14d, side: THREE.DoubleSide,
                                      transparent: true, opacity: 0.55 })
      );
      const edge = new THREE.LineLoop(
        new THREE.BufferGeometry().setFromPoints(outline),
        new THREE.LineBasicMaterial({ color: 0xffe14d })
      );
      objects.push(board, edge);
      const div = document.createElement("div");
      div.textContent = t.name;
      labels.appendChild(div);
      targetLabels.push({ div, at: outline[0].clone().add(outline[2]).multiplyScalar(0.5) });
    }
    addLayer("targets", `AprilGrid targets (${sceneDoc.targets.length})`, objects, "#ffe14d");
  }

  // Measuring: two clicks on the mesh (or the points when the mesh is off).
  const raycaster = new THREE.Raycaster();
  raycaster.params.Points.threshold = glyph / 2;
  let measuring = false;
  let picks = [];
  const measureGroup = new THREE.Group();
  scene.add(measureGroup);
  function clearMeasure() {
    picks = [];
    measureGroup.clear();
  }
  function pick(clientX, clientY) {
    const rect = canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(
      ((clientX - rect.left) / rect.width) * 2 - 1,
      -((clientY - rect.top) / rect.height) * 2 + 1
    );
    raycaster.setFromCamera(ndc, camera);
    const targets = [meshObject, pointsObject].filter((o) => o && o.visible);
    const hits = raycaster.intersectObjects(targets, false);
    return hits.length ? hits[0].point.clone() : null;
  }
  function marker(at) {
    const dot = new THREE.Mesh(
      new THREE.SphereGeometry(glyph * 0.35, 12, 8),
      new THREE.MeshBasicMaterial({ color: 0xff3355, depthTest: false })
    );
    dot.position.copy(at);
    dot.renderOrder = 10;
    measureGroup.add(dot);
  }

  // Panel: layer toggles, views, measure.
  const title = document.createElement("div");
  title.innerHTML = "<b>Layers</b>";
  panel.appendChild(title);
  for (const [name, layer] of Object.entries(layers)) {
    const row = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox";
    box.id = "wm-layer-" + name.replace(/[^a-zA-Z0-9_-]/g, "_");
    box.dataset.layer = name;
    box.checked = !hidden.has(name);
    box.addEventListener("change", () => { applyLayers(); render(); });
    row.appendChild(box);
    if (layer.swatch) {
      const sw = document.createElement("span");
      sw.className = "wm-swatch";
      sw.style.background = layer.swatch;
      row.appendChild(sw);
    }
    row.appendChild(document.createTextNode(layer.label));
    panel.appendChild(row);
  }
  if (sceneDoc.sessions.length) {
    const row = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox";
    box.id = "wm-layer-keyframes";
    box.checked = !hidden.has("keyframes");
    box.addEventListener("change", () => { applyLayers(); render(); });
    row.appendChild(box);
    row.appendChild(document.createTextNode("keyframe cameras"));
    panel.appendChild(row);
  }
  if (coverageColours) {
    const row = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox";
    box.id = "wm-coverage";
    box.checked = hash.get("colour") === "coverage";
    box.addEventListener("change", () => { applyLayers(); render(); });
    row.appendChild(box);
    row.appendChild(document.createTextNode("mesh coloured by coverage"));
    panel.appendChild(row);
  }
  function applyLayers() {
    const coverageBox = document.getElementById("wm-coverage");
    if (coverageBox) {
      const geometry = meshObject.geometry;
      const wanted = coverageBox.checked ? coverageColours : photoColours;
      if (wanted) geometry.setAttribute("color", wanted);
      else geometry.deleteAttribute("color");
      meshObject.material.vertexColors = !!wanted;
      meshObject.material.color.set(wanted ? 0xffffff : 0xb0b0b0);
      meshObject.material.needsUpdate = true;
    }
    for (const box of panel.querySelectorAll("input[data-layer]")) {
      for (const o of layers[box.dataset.layer].objects) o.visible = box.checked;
    }
    const frustaBox = document.getElementById("wm-layer-keyframes");
    if (frustaBox && !frustaBox.checked) {
      for (const layer of Object.values(layers)) {
        for (const o of layer.objects) if (o.userData.keyframes) o.visible = false;
      }
    }
    const targetsBox = document.getElementById("wm-layer-targets");
    for (const l of targetLabels) l.div.style.display = targetsBox && targetsBox.checked ? "" : "none";
  }
  const buttons = document.createElement("div");
  for (const [label, view] of [["top", "top"], ["side", "side"], ["oblique", "oblique"]]) {
    const b = document.createElement("button");
    b.textContent = label;
    b.addEventListener("click", () => { setView(view); render(); });
    buttons.appendChild(b);
  }
  const measureButton = document.createElement("button");
  measureButton.id = "wm-measure";
  measureButton.textContent = "measure";
  measureButton.title = "click two points on the model";
  measureButton.addEventListener("click", () => {
    measuring = !measuring;
    container.classList.toggle("measuring", measuring);
    measureButton.textContent = measuring ? "measuring: click 2 points" : "measure";
    clearMeasure();
    render();
  });
  buttons.appendChild(measureButton);
  panel.appendChild(buttons);
  const result = document.createElement("div");
  result.id = "wm-measure-result";
  panel.appendChild(result);
  const help = document.createElement("div");
  help.className = "small";
  help.textContent = "drag: orbit; right-drag: pan; wheel: zoom";
  panel.appendChild(help);

  const controls = new THREE.OrbitControls(camera, canvas);
  controls.enableDamping = false;
  controls.screenSpacePanning = true;
  function setView(view) {
    const zoom = Math.max(Number(hash.get("zoom")) || 1, 0.05);
    const d = (radius * 1.8) / zoom;
    const dirs = { top: [0, -1e-3, 1], side: [0, -1, 0.08], oblique: [0.7, -1.0, 0.8] };
    const dir = new THREE.Vector3(...(dirs[view] || dirs.oblique)).normalize();
    camera.position.copy(centre).addScaledVector(dir, d);
    controls.target.copy(centre);
    camera.near = radius / 200;
    camera.far = radius * 50;
    camera.updateProjectionMatrix();
    controls.update();
  }

  // Scale bar: 1, 2 or 5 x 10^k metres about 80-200 px long at the orbit centre's depth.
  const bar = document.querySelector("#wm-scalebar div");
  const barText = document.querySelector("#wm-scalebar span");
  function updateScaleBar() {
    const distance = camera.position.distanceTo(controls.target);
    const height = canvas.clientHeight || 1;
    const pxPerM = height / (2 * distance * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)));
    const want = 120 / pxPerM;
    const power = Math.pow(10, Math.floor(Math.log10(want)));
    let length = power;
    for (const m of [1, 2, 5, 10]) if (m * power <= want * 1.6) length = m * power;
    bar.style.width = (length * pxPerM).toFixed(0) + "px";
    barText.textContent = length >= 1 ? `${length} m` : `${(length * 100).toFixed(0)} cm`;
  }

  function resize() {
    const w = container.clientWidth, h = container.clientHeight;
    renderer.setSize(w, h, false);
    camera.aspect = w / Math.max(h, 1);
    camera.updateProjectionMatrix();
  }
  function render() {
    renderer.render(scene, camera);
    updateScaleBar();
    const w = canvas.clientWidth, h = canvas.clientHeight;
    for (const l of targetLabels) {
      const p = l.at.clone().project(camera);
      l.div.style.left = ((p.x + 1) / 2 * w).toFixed(0) + "px";
      l.div.style.top = ((1 - p.y) / 2 * h).toFixed(0) + "px";
      l.div.style.visibility = p.z < 1 ? "visible" : "hidden";
    }
    api.frames += 1;
    document.body.dataset.viewerFrames = String(api.frames);
  }
  controls.addEventListener("change", render);
  window.addEventListener("resize", () => { resize(); render(); });

  let downAt = null;
  canvas.addEventListener("pointerdown", (e) => { downAt = [e.clientX, e.clientY]; });
  canvas.addEventListener("pointerup", (e) => {
    if (!measuring || !downAt) return;
    // A drag is an orbit, not a click.
    if (Math.hypot(e.clientX - downAt[0], e.clientY - downAt[1]) > 4) return;
    const at = pick(e.clientX, e.clientY);
    if (!at) return;
    if (picks.length >= 2) clearMeasure();
    picks.push(at);
    marker(at);
    if (picks.length === 2) {
      const d = picks[0].distanceTo(picks[1]);
      api.lastMeasure_m = d;
      measureGroup.add(new THREE.Line(
        new THREE.BufferGeometry().setFromPoints(picks),
        new THREE.LineBasicMaterial({ color: 0xff3355, depthTest: false })
      ));
      const a = picks[0].clone().add(origin), b = picks[1].clone().add(origin);
      result.textContent = `${d.toFixed(3)} m (dz ${(b.z - a.z).toFixed(3)} m)`;
    } else {
      result.textContent = "click a second point";
    }
    render();
  });

  // World point (W, m) -> page pixel, for the tests' clicks.
  api.toScreen = function (xyz) {
    const p = local(xyz).project(camera);
    const rect = canvas.getBoundingClientRect();
    return [rect.left + (p.x + 1) / 2 * rect.width, rect.top + (1 - p.y) / 2 * rect.height];
  };
  api.setView = function (view) { setView(view); render(); };

  document.getElementById("wm-info").textContent = info
    .concat(sceneDoc.notes, ["the scale bar holds at the orbit centre's distance."])
    .join("; ");
  resize();
  setView(hash.get("view") || "oblique");
  applyLayers();
  render();
  api.ready = true;
})();
