// omniscan's splat viewer: the page's models (SPZ, inlined as base64) shown
// with Spark's renderer (vendored in viewer-lib.js), orbit / pan / zoom, a
// reset button, one button per model and one for all side by side, and
// markers (the defect regions of an inspection). Everything the page needs
// is in the page: it opens from file:// and asks nothing of the network.
//
// The scene is the models' own frame (the pipeline's: metres, z up): SPZ
// stores RUB axes, so each mesh is turned back by a half turn about x.
// window.omniscanViewer is the page's interface for tests and scripts:
// setCamera, setBackground, show, and framesDrawn / ready for "drawn".
(async function () {
  "use strict";
  // The library travels gzipped in base64 (a third of its size); the
  // browser's own DecompressionStream unpacks it into a script element.
  try {
    const packed = document.getElementById("omniscan-viewer-lib").textContent.trim();
    const bytes = Uint8Array.from(atob(packed), (c) => c.charCodeAt(0));
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
    const script = document.createElement("script");
    script.textContent = await new Response(stream).text();
    document.head.appendChild(script);
  } catch (e) {
    console.error("omniscan viewer: the library could not be unpacked", e);
  }
  const lib = window.OmniscanViewerLib;
  const config = JSON.parse(document.getElementById("omniscan-viewer-config").textContent);
  const root = document.getElementById("omniscan-viewer");
  const canvasBox = root.querySelector(".ov-canvas");
  const status = root.querySelector(".ov-status");
  const api = { framesDrawn: 0, loaded: false, error: null };
  window.omniscanViewer = api;

  function fail(message) {
    api.error = message;
    status.textContent = message;
    status.classList.add("ov-error");
  }
  if (!lib) {
    fail("The viewer library did not load.");
    return;
  }
  const { THREE, OrbitControls, SparkRenderer, SplatMesh } = lib;
  let renderer;
  try {
    renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
  } catch (e) {
    fail("This browser cannot draw WebGL2, which the viewer needs: " + e.message);
    return;
  }
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  canvasBox.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color().setRGB(config.background[0], config.background[1], config.background[2], THREE.SRGBColorSpace);
  scene.add(new SparkRenderer({ renderer }));
  const camera = new THREE.PerspectiveCamera(50, 1, 0.001, 1000);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.enableDamping = false;

  // Base64 to bytes in slices, yielding between them, so a large model
  // does not hold the page while it decodes.
  async function decode(text) {
    const clean = text.replace(/\s+/g, "");
    const bytes = new Uint8Array(Math.floor((clean.length * 3) / 4) - (clean.endsWith("==") ? 2 : clean.endsWith("=") ? 1 : 0));
    const slice = 4 * 262144;
    let at = 0;
    for (let i = 0; i < clean.length; i += slice) {
      const part = atob(clean.slice(i, i + slice));
      for (let j = 0; j < part.length; j++) bytes[at++] = part.charCodeAt(j);
      await new Promise((r) => setTimeout(r, 0));
    }
    return bytes;
  }

  const models = [];
  const markerGroups = [];
  const labels = [];

  function addMarkers(model, group) {
    const markers = new THREE.Group();
    group.add(markers);
    markerGroups.push(markers);
    for (const m of model.markers) {
      const colour = new THREE.Color(m.colour[0] / 255, m.colour[1] / 255, m.colour[2] / 255);
      const sphere = new THREE.Mesh(
        new THREE.SphereGeometry(m.radius, 24, 16),
        new THREE.MeshBasicMaterial({ color: colour, wireframe: true, depthTest: false, transparent: true, opacity: 0.9 }),
      );
      sphere.renderOrder = 10;
      sphere.position.set(m.position[0], m.position[1], m.position[2]);
      markers.add(sphere);
      const label = document.createElement("div");
      label.className = "ov-label";
      label.textContent = m.label;
      label.style.borderColor = "#" + colour.getHexString();
      canvasBox.appendChild(label);
      labels.push({ element: label, object: sphere, model: group });
    }
  }

  function layout(visible) {
    // Side by side along x when several are shown, each at its own centre.
    const shown = models.filter((m) => visible.includes(m.index));
    const gap = 2.4 * Math.max(...shown.map((m) => m.info.radius));
    shown.forEach((m, k) => {
      const shift = (k - (shown.length - 1) / 2) * gap;
      m.group.position.set(shift, 0, 0);
    });
    for (const m of models) m.group.visible = visible.includes(m.index);
    for (const l of labels) l.element.style.display = l.model.visible ? "" : "none";
  }

  function frame(visible) {
    const shown = models.filter((m) => visible.includes(m.index));
    if (shown.length === 1) {
      setCamera(shown[0].info.camera);
      return;
    }
    if (shown.length === 0) return;
    const box = new THREE.Box3();
    for (const m of shown) {
      const c = new THREE.Vector3(...m.info.centre).add(m.group.position);
      box.expandByPoint(c.clone().addScalar(m.info.radius));
      box.expandByPoint(c.clone().addScalar(-m.info.radius));
    }
    const centre = box.getCenter(new THREE.Vector3());
    const radius = box.getSize(new THREE.Vector3()).length() / 2 / Math.sqrt(3) * 1.2;
    const distance = (radius / Math.tan((25 * Math.PI) / 180)) * 1.5;
    const dir = new THREE.Vector3(0, -Math.cos(0.35), Math.sin(0.35));
    setCamera({
      eye: centre.clone().addScaledVector(dir, distance).toArray(),
      target: centre.toArray(),
      up: config.up,
      horizontal_fov_deg: 50,
    });
  }

  let visible = [];
  function show(indices) {
    visible = indices;
    layout(indices);
    frame(indices);
    for (const b of root.querySelectorAll(".ov-buttons button[data-show]")) {
      b.classList.toggle("ov-on", b.dataset.show === indices.join(","));
    }
  }

  // The camera as the CPU renderer's orbit takes it: an eye, a target, an
  // up and the horizontal field of view (the vertical one follows the
  // canvas's aspect).
  function setCamera(c) {
    camera.up.set(c.up[0], c.up[1], c.up[2]);
    camera.position.set(c.eye[0], c.eye[1], c.eye[2]);
    controls.target.set(c.target[0], c.target[1], c.target[2]);
    api.horizontalFov = c.horizontal_fov_deg;
    const distance = camera.position.distanceTo(controls.target);
    camera.near = distance * 0.01;
    camera.far = distance * 100;
    resize();
    camera.lookAt(controls.target);
    controls.update();
  }

  function resize() {
    const w = canvasBox.clientWidth || 1;
    const h = canvasBox.clientHeight || 1;
    renderer.setSize(w, h, false);
    renderer.domElement.style.width = w + "px";
    renderer.domElement.style.height = h + "px";
    camera.aspect = w / h;
    const half = ((api.horizontalFov || 50) * Math.PI) / 360;
    camera.fov = (2 * Math.atan(Math.tan(half) / camera.aspect) * 180) / Math.PI;
    camera.updateProjectionMatrix();
  }
  window.addEventListener("resize", resize);

  function placeLabels() {
    const w = canvasBox.clientWidth;
    const h = canvasBox.clientHeight;
    const p = new THREE.Vector3();
    for (const l of labels) {
      if (!l.model.visible) continue;
      l.object.getWorldPosition(p);
      p.project(camera);
      const behind = p.z > 1;
      l.element.style.display = behind ? "none" : "";
      l.element.style.left = ((p.x + 1) / 2) * w + "px";
      l.element.style.top = ((1 - p.y) / 2) * h + "px";
    }
  }

  api.setCamera = setCamera;
  api.show = show;
  api.setBackground = (rgb) => scene.background.setRGB(rgb[0], rgb[1], rgb[2], THREE.SRGBColorSpace);
  api.setMarkersVisible = (on) => {
    for (const g of markerGroups) g.visible = on;
    for (const l of labels) l.element.style.visibility = on ? "" : "hidden";
  };
  api.ready = (async () => {
    try {
      for (const [index, info] of config.models.entries()) {
        status.textContent = `Loading ${info.name} (${info.splats.toLocaleString()} splats)…`;
        const bytes = await decode(document.getElementById(info.data_id).textContent);
        const mesh = new SplatMesh({ fileBytes: bytes, fileName: "model.spz" });
        await mesh.initialized;
        // SPZ's RUB axes back to the model's own: a half turn about x.
        mesh.quaternion.set(1, 0, 0, 0);
        const group = new THREE.Group();
        group.add(mesh);
        addMarkers(info, group);
        scene.add(group);
        models.push({ index, info, group, mesh });
      }
      show(config.models.map((_, i) => i));
      status.textContent = "";
      api.loaded = true;
    } catch (e) {
      fail("The model could not be shown: " + (e && e.message ? e.message : e));
      throw e;
    }
  })();

  for (const b of root.querySelectorAll(".ov-buttons button[data-show]")) {
    b.addEventListener("click", () => show(b.dataset.show.split(",").map(Number)));
  }
  const reset = root.querySelector(".ov-reset");
  if (reset) reset.addEventListener("click", () => frame(visible));
  const markerToggle = root.querySelector(".ov-markers");
  if (markerToggle) {
    markerToggle.addEventListener("change", () => api.setMarkersVisible(markerToggle.checked));
  }

  renderer.setAnimationLoop(() => {
    controls.update();
    renderer.render(scene, camera);
    placeLabels();
    if (api.loaded) api.framesDrawn++;
  });
})();
