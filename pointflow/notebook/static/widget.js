// pointflow's notebook view (an anywidget): the live frame of one view of the render
// stage, steered with the page's controls (pointflow/serve/static/view.js: drag orbits,
// shift- or right-drag pans, the wheel zooms, a click picks, f fits). Frames come from the
// kernel as custom messages with one buffer (JPEG while moving, PNG when still); each one
// drawn is acknowledged, which lets the kernel ask for the next (at most two in flight).

function el(tag, attrs = {}, parent = null) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) if (k === "text") e.textContent = v; else e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}

function fmt(v) {
  return typeof v === "number" ? (Math.abs(v) >= 1e4 || (v !== 0 && Math.abs(v) < 1e-3) ? v.toExponential(3) : v.toFixed(3)) : String(v);
}

function render({ model, el: root }) {
  root.classList.add("pointflow-view");
  const bar = el("div", { class: "pf-bar" }, root);
  const fit = el("button", { text: "Fit", title: "frame the data (f)" }, bar);
  const colorBy = el("select", { title: "colour by" }, bar);
  const cmap = el("select", { title: "colormap" }, bar);
  const size = el("input", { type: "number", min: "1", max: "64", step: "1", value: "2", title: "point size (px)" }, bar);
  const edlBox = el("label", { text: " EDL" }, bar);
  const edl = el("input", { type: "checkbox" });
  edlBox.prepend(edl);
  const canvas = el("canvas", { class: "pf-canvas", tabindex: "0" }, root);
  canvas.width = model.get("width"); canvas.height = model.get("height");
  canvas.style.width = `${model.get("width")}px`; canvas.style.height = `${model.get("height")}px`;
  const g = canvas.getContext("2d");
  const stats = el("div", { class: "pf-stats", text: "waiting for the first frame…" }, root);
  const info = el("pre", { class: "pf-info" }, root);
  info.hidden = true;
  let shown = 0, drawing = Promise.resolve(), alive = true;

  const fill = (sel, names, value) => {
    sel.innerHTML = "";
    for (const n of names) el("option", { value: n, text: n }, sel);
    if (value != null) sel.value = value;
  };
  fill(colorBy, model.get("color_by_options")); fill(cmap, model.get("colormaps"));
  const send = (m) => { if (alive) model.send(m); };
  const control = (m) => send({ type: "control", msg: m });

  function onFrame(head, buffer) {
    const blob = new Blob([buffer], { type: head.mime });
    drawing = drawing.then(() => createImageBitmap(blob)).then((bmp) => {
      if (canvas.width !== bmp.width || canvas.height !== bmp.height) { canvas.width = bmp.width; canvas.height = bmp.height; }
      g.drawImage(bmp, 0, 0);
      bmp.close();
      shown++;
      canvas.dataset.frames = String(shown);
      canvas.dataset.mime = head.mime;
      canvas.dataset.version = String(head.version);
    }).catch(() => {}).then(() => send({ type: "ack", seq: head.seq }));
  }

  function onState(s) {
    if (!s || !s.style) return;
    const cb = s.style.color_by == null ? "none" : s.style.color_by;
    if (![...colorBy.options].some((o) => o.value === cb)) el("option", { value: cb, text: cb }, colorBy);
    colorBy.value = cb; cmap.value = s.style.colormap; size.value = s.style.point_size; edl.checked = !!s.style.edl;
  }

  function showPick(m) {
    const p = m.point;
    if (!p) { info.textContent = "no point there"; info.hidden = false; return; }
    const pos = p.position || [];
    let text = `x ${fmt(pos[0])}\ny ${fmt(pos[1])}\nz ${fmt(pos[2])}`;
    if (m.source) text += `\nsource ${m.source}`;
    for (const [k, v] of Object.entries(p.channels || {})) text += `\n${k} ${fmt(v)}`;
    info.textContent = text; info.hidden = false;
    info.dataset.position = JSON.stringify(pos);
  }

  const onMsg = (msg, buffers) => {
    if (msg.type === "frame") onFrame(msg, buffers[0]);
    else if (msg.type === "reply") onState(msg);
    else if (msg.type === "pick") showPick(msg);
    else if (msg.type === "error") { info.textContent = `refused: ${msg.key ? msg.key + ": " : ""}${msg.error}`; info.hidden = false; }
    else if (msg.type === "stats") {
      stats.textContent = [`points ${msg.points}`, `render ${msg.fps} fps`, `view ${msg.view_fps} fps`,
        `${Math.round((msg.bytes_per_frame || 0) / 1024)} KB/frame`, `encode ${msg.encode_ms} ms`,
        `sources ${(msg.sources || []).join(", ")}`].join(" · ");
    }
  };
  model.on("msg:custom", onMsg);

  fit.onclick = () => control({ cmd: "fit" });
  colorBy.onchange = () => control({ cmd: "style", color_by: colorBy.value });
  cmap.onchange = () => control({ cmd: "style", colormap: cmap.value });
  size.onchange = () => control({ cmd: "style", point_size: Number(size.value) });
  edl.onchange = () => control({ cmd: "style", edl: edl.checked });

  // drags, wheel, pinch and keys: the page's gestures.js, prepended to this module by widget.py
  pointflowGestures(canvas, control, (x, y) => send({ type: "pick", x, y }),
                    (e) => { if (e.key !== "f") return false; fit.click(); return true; });

  send({ type: "hello" });
  return () => { alive = false; model.off("msg:custom", onMsg); };
}

export default { render };
