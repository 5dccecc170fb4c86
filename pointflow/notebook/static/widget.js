// pointflow's notebook view (an anywidget): the live frame of one view of the render
// stage, steered with the page's controls (pointflow/serve/static/view.js: drag orbits,
// shift- or right-drag pans, the wheel zooms, a click picks or measures, f fits, r resets,
// space plays or pauses a replay, ? shows the help). Frames come from the kernel as custom
// messages with one buffer (JPEG while moving, PNG when still); each one drawn is
// acknowledged, which lets the kernel ask for the next (at most two in flight). The model's
// `stopped` says the pipeline ended: the last frame stays, the controls are switched off.
// Over the picture: the page's overlay.js (axes, grid, compass, pick and measure marks, from
// the camera each frame was drawn with) and the colour legend, when the frames carry them;
// without them, the marks are drawn where the clicks were and cleared when the camera moves.

function el(tag, attrs = {}, parent = null) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) if (k === "text") e.textContent = v; else e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}

function fmt(v) {
  return typeof v === "number" ? (Math.abs(v) >= 1e4 || (v !== 0 && Math.abs(v) < 1e-3) ? v.toExponential(3) : v.toFixed(3)) : String(v);
}
function fmtFull(v) { return pointflowOverlay.fmtFull(v); }  // (overlay.js: both views show picks alike)

// a control with its name before it: <label>Name <control></label>
function labelled(text, control, parent, title) {
  const l = el("label", { class: "pf-field", title: title || text }, parent);
  el("span", { class: "pf-label", text }, l);
  l.appendChild(control);
  return l;
}

const HELP = [
  ["drag", "orbit"], ["shift-drag, right-drag", "pan"], ["wheel, pinch", "zoom"],
  ["click", "pick a point (Click: measure — two clicks, their distance)"],
  ["arrows", "orbit (shift: pan)"], ["+ / -", "zoom"], ["f", "fit: frame the data"],
  ["r", "reset: fit and the starting style"], ["space", "play / pause a replay"],
  ["a, g, c, l", "axes, grid, compass, legend on / off"], ["?", "this help"],
];

function render({ model, el: root }) {
  root.classList.add("pointflow-view");
  const bar = el("div", { class: "pf-bar" }, root);
  const fit = el("button", { text: "Fit", title: "frame the data (f)" }, bar);
  const reset = el("button", { text: "Reset", title: "fit, and the style the view started with (r)" }, bar);
  const mode = el("select", { class: "pf-mode" });
  for (const m of ["pick", "measure"]) el("option", { value: m, text: m }, mode);
  labelled("Click", mode, bar, "what a click on the picture does");
  const colorBy = el("select", { class: "pf-color-by" });
  labelled("Colour", colorBy, bar, "the channel the colour shows");
  const cmap = el("select", { class: "pf-colormap" });
  labelled("Map", cmap, bar, "colormap");
  const size = el("input", { class: "pf-size", type: "range", min: "1", max: "12", step: "1", value: "2" });
  // the style is not known until the view's first state arrives: no number is shown before it
  const sizeVal = el("span", { class: "pf-value", text: "… px" });
  labelled("Size", size, bar, "point size (pixels)").appendChild(sizeVal);
  const edl = el("input", { class: "pf-edl", type: "checkbox" });
  labelled("EDL", edl, bar, "eye-dome lighting: shades depth edges");
  const showBox = el("span", { class: "pf-show", title: "drawn over the picture from the camera it was drawn with" }, bar);
  el("span", { class: "pf-label", text: "Show" }, showBox);
  const show = { axes: true, grid: true, compass: true, legend: true }, showInput = {};
  for (const k of Object.keys(show)) {
    const l = el("label", { class: "pf-field" }, showBox);
    showInput[k] = el("input", { type: "checkbox", class: `pf-show-${k}` }, l);
    showInput[k].checked = true;
    el("span", { text: k }, l);
  }
  showBox.hidden = true;  // until a frame carries its camera (the overlay has something to draw from)
  const helpBtn = el("button", { text: "?", title: "gestures and keys (?)", class: "pf-help-button" }, bar);

  const stage = el("div", { class: "pf-stage" }, root);
  const canvas = el("canvas", { class: "pf-canvas", tabindex: "0" }, stage);
  const marks = el("canvas", { class: "pf-marks" }, stage);  // pick marker and measure line
  for (const c of [canvas, marks]) {
    c.width = model.get("width"); c.height = model.get("height");
    c.style.width = `${model.get("width")}px`; c.style.height = `${model.get("height")}px`;
  }
  const g = canvas.getContext("2d"), mg = marks.getContext("2d");
  const ended = el("div", { class: "pf-ended" }, stage);
  ended.hidden = true;
  const help = el("div", { class: "pf-help" }, stage);
  for (const [k, v] of HELP) { const r = el("div", {}, help); el("b", { text: k }, r); el("span", { text: " " + v }, r); }
  help.hidden = true;
  const legend = el("div", { class: "pf-legend" }, stage);
  const legendTitle = el("div", { class: "pf-legend-title" }, legend);
  const legendBar = el("canvas", { class: "pf-legend-bar", width: "256", height: "1" }, legend);
  const legendTicks = el("div", { class: "pf-legend-ticks" }, legend);
  legend.hidden = true;

  const timeline = el("div", { class: "pf-timeline" }, root);
  const play = el("button", { class: "pf-play", text: "Pause", title: "play / pause (space)" }, timeline);
  const step = el("button", { class: "pf-step", text: "Step", title: "send the next message (stays paused)" }, timeline);
  const seek = el("input", { class: "pf-seek", type: "range", min: "0", max: "1000", value: "0" });
  labelled("Time", seek, timeline, "seek in the recording");
  const position = el("span", { class: "pf-position", text: "0.0 s" }, timeline);
  const rate = el("select", { class: "pf-rate" });
  for (const r of ["0.25", "0.5", "1", "2", "4"]) el("option", { value: r, text: `${r}×` }, rate);
  rate.value = "1";
  labelled("Speed", rate, timeline, "times as fast as recorded");
  const loop = el("input", { class: "pf-loop", type: "checkbox" });
  labelled("Loop", loop, timeline, "start again at the end");
  timeline.hidden = true;

  const stats = el("div", { class: "pf-stats", text: "waiting for the first frame…" }, root);
  const info = el("pre", { class: "pf-info" }, root);
  info.hidden = true;
  let shown = 0, drawing = Promise.resolve(), alive = true, state0 = null, lastCamera = null;
  let measureA = null, playbackState = null, seeking = false, pbWaiting = 0, pickAt = [0, 0];
  // marks in world coordinates (overlay.js projects them with each frame's camera) and where
  // the clicks were (drawn as they are when the frames carry no camera)
  let wmarks = { pick: null, measure: [] }, marksPx = { pick: null, measure: [] }, frameCam = null, frameFollow = null, frameUnits = null;
  const overlay = typeof pointflowOverlay !== "undefined" ? pointflowOverlay : null;

  const fill = (sel, names, value) => {
    sel.innerHTML = "";
    for (const n of names) el("option", { value: n, text: n }, sel);
    if (value != null) sel.value = value;
  };
  fill(colorBy, model.get("color_by_options")); fill(cmap, model.get("colormaps"));
  const stopped = () => !!model.get("stopped");
  const send = (m) => { if (alive && !stopped()) model.send(m); };
  const control = (m) => {
    // the camera moves: marks drawn where the clicks were would lie (projected ones follow it)
    if (!frameCam && !["style", "view_state", "visible"].includes(m.cmd)) clearMarks();
    send({ type: "control", msg: m });
  };

  // ------------------------------------------------------------------ frames
  function onFrame(head, buffer) {
    const blob = new Blob([buffer], { type: head.mime });
    drawing = drawing.then(() => createImageBitmap(blob)).then((bmp) => {
      if (canvas.width !== bmp.width || canvas.height !== bmp.height) {
        canvas.width = marks.width = bmp.width; canvas.height = marks.height = bmp.height;
      }
      g.drawImage(bmp, 0, 0);
      bmp.close();
      shown++;
      canvas.dataset.frames = String(shown);
      canvas.dataset.mime = head.mime;
      canvas.dataset.version = String(head.version);
      frameCam = head.camera || null; frameFollow = head.follow || null; frameUnits = head.units || null;
      showBox.hidden = !(overlay && frameCam);
      drawMarks();
      if ("legend" in head) drawLegend(head.legend);
    }).catch(() => {}).then(() => send({ type: "ack", seq: head.seq }));
  }

  function onState(s) {
    if (!s || !s.style) return;
    if (!state0) state0 = s;
    const cb = s.style.color_by == null ? "none" : s.style.color_by;
    if (![...colorBy.options].some((o) => o.value === cb)) el("option", { value: cb, text: cb }, colorBy);
    colorBy.value = cb; cmap.value = s.style.colormap; size.value = s.style.point_size; edl.checked = !!s.style.edl;
    sizeVal.textContent = `${s.style.point_size} px`;
    root.dataset.state = "1";
    const cam = JSON.stringify(s.camera || null);
    if (!frameCam && lastCamera !== null && cam !== lastCamera) clearMarks();
    lastCamera = cam;
  }

  // ------------------------------------------------------------------ pick and measure
  function clearMarks() {
    wmarks = { pick: null, measure: [] }; marksPx = { pick: null, measure: [] };
    delete canvas.dataset.distance;
    if (measureA) { measureA = null; info.hidden = true; }
    drawMarks();
  }

  function mark(x, y) {
    mg.lineWidth = 2; mg.strokeStyle = "#ffffff"; mg.fillStyle = "#ff3366";
    mg.beginPath(); mg.arc(x, y, 5, 0, 2 * Math.PI); mg.fill(); mg.stroke();
  }

  // the overlay from the frame's camera, else the marks where the clicks were
  function drawMarks() {
    if (overlay && frameCam) {
      overlay.draw(mg, frameCam, marks.width, marks.height, { axes: show.axes, grid: show.grid, compass: show.compass,
                                                              marks: wmarks, follow: frameFollow, units: frameUnits });
      canvas.dataset.overlay = "1";
      return;
    }
    mg.clearRect(0, 0, marks.width, marks.height);
    const m = marksPx.measure;
    if (m.length === 2) {
      const d = Math.hypot(...[0, 1, 2].map((i) => wmarks.measure[1][i] - wmarks.measure[0][i]));
      mg.lineWidth = 2; mg.strokeStyle = "#ffdd33";
      mg.beginPath(); mg.moveTo(m[0][0], m[0][1]); mg.lineTo(m[1][0], m[1][1]); mg.stroke();
      mg.font = "bold 13px system-ui, sans-serif";
      const tx = (m[0][0] + m[1][0]) / 2 + 6, ty = (m[0][1] + m[1][1]) / 2 - 6;
      mg.lineWidth = 3; mg.strokeStyle = "#000"; mg.strokeText(fmt(d), tx, ty);
      mg.fillStyle = "#ffdd33"; mg.fillText(fmt(d), tx, ty);
    }
    for (const p of m) mark(p[0], p[1]);
    if (marksPx.pick) mark(marksPx.pick[0], marksPx.pick[1]);
  }

  // ------------------------------------------------------------------ the colour legend
  const lutCache = {};
  function lutRgba(name) {
    return overlay ? overlay.decodeLut((model.get("luts") || {})[name]) : null;
  }
  let legendKey = "";
  function drawLegend(lg) {
    const lut = lg && (lutCache[lg.colormap] || (lutCache[lg.colormap] = lutRgba(lg.colormap)));
    if (!show.legend || !lg || !lut || lg.range[0] == null || lg.range[1] == null) { legend.hidden = true; return; }
    legend.hidden = false;
    const [lo, hi] = lg.range, key = JSON.stringify(lg);
    if (key === legendKey) return;
    legendKey = key;
    legend.dataset.lo = String(lo); legend.dataset.hi = String(hi); legend.dataset.colormap = lg.colormap;
    legendTitle.textContent = overlay ? overlay.legendTitle(lg) : lg.color_by;
    legendBar.getContext("2d").putImageData(new ImageData(lut, 256, 1), 0, 0);
    legendTicks.innerHTML = "";
    const put = (cls, v, frac) => {
      const t = el("span", { class: cls, text: overlay ? overlay.fmtTick(v, hi - lo) : fmt(v) }, legendTicks);
      if (cls === "mid") t.style.left = `${100 * frac}%`;
      el("i", {}, legendTicks).style.left = `${Math.min(99.5, 100 * frac)}%`;
    };
    put("lo", lo, 0); put("hi", hi, 1);
    if (hi > lo && overlay) {  // round values between, where their labels do not run into the ends'
      const stepV = overlay.niceStep((hi - lo) / 4);
      for (let v = Math.ceil(lo / stepV) * stepV; v < hi; v += stepV) {
        const f = (v - lo) / (hi - lo);
        if (f > 0.25 && f < 0.75) put("mid", +v.toPrecision(6), f);
      }
    }
  }
  for (const k of Object.keys(show)) {
    showInput[k].onchange = () => {
      show[k] = showInput[k].checked;
      drawMarks();
      if (k === "legend") { legendKey = ""; if (!show.legend) legend.hidden = true; }
    };
  }
  const toggle = (k) => { showInput[k].checked = !showInput[k].checked; showInput[k].onchange(); };

  function showPick(m) {
    const p = m.point;
    if (!p) { info.textContent = "no point there"; info.hidden = false; return; }
    const pos = p.position || [];
    const at = pickAt;  // the canvas pixel clicked (picks are answered in order)
    let text = `x ${fmtFull(pos[0])}\ny ${fmtFull(pos[1])}\nz ${fmtFull(pos[2])}`;
    if (m.source) text += `\nsource: ${m.source}`;
    for (const [k, v] of Object.entries(p.channels || {})) text += `\n${k}: ${fmtFull(v)}`;
    if (mode.value === "measure" && measureA) {
      const a = measureA.pos;
      const d = Math.hypot(pos[0] - a[0], pos[1] - a[1], pos[2] - a[2]);
      wmarks = { pick: null, measure: [a, pos] }; marksPx = { pick: null, measure: [measureA.at, at] };
      text = `distance ${pointflowOverlay.fmtDistance(d, frameUnits)}\nfrom ${a.map(fmtFull).join(", ")}\nto   ${pos.map(fmtFull).join(", ")}`;
      measureA = null;
      canvas.dataset.distance = String(d);
    } else if (mode.value === "measure") {
      wmarks = { pick: pos, measure: [] }; marksPx = { pick: at, measure: [] };
      measureA = { pos, at };
      text = "measure: first point\n" + text + "\n(click the second)";
    } else {
      wmarks = { pick: pos, measure: [] }; marksPx = { pick: at, measure: [] };
    }
    drawMarks();
    info.textContent = text; info.hidden = false;
    info.dataset.position = JSON.stringify(pos);
  }

  // ------------------------------------------------------------------ timeline
  const playback = (args) => { if (pbWaiting < 2) { pbWaiting++; send({ type: "playback", args }); } };
  function onPlayback(m) {
    const states = Object.values(m.sources || {}).filter(Boolean);
    if (!states.length) return;
    const s = states[0]; playbackState = s;
    play.textContent = s.paused ? "Play" : "Pause";
    loop.checked = !!s.loop;
    if (s.rate > 0) rate.value = [...rate.options].some((o) => Number(o.value) === s.rate) ? String(s.rate) : rate.value;
    position.textContent = `${s.position_s.toFixed(1)}${s.duration_s ? " / " + s.duration_s.toFixed(1) : ""} s`
      + (s.at_end ? " (end)" : "");
    if (!seeking && s.duration_s) seek.value = String(Math.round(1000 * s.position_s / s.duration_s));
    timeline.dataset.paused = String(s.paused);
    timeline.dataset.position = String(s.position_s);
    timeline.dataset.index = String(s.index);
  }
  play.onclick = () => playback({ paused: !(playbackState && playbackState.paused) });
  step.onclick = () => playback({ step: 1 });
  seek.oninput = () => { seeking = true; };
  seek.onchange = () => {
    seeking = false;
    // paused, the sought message goes once (ingest/playback.py), so the picture shows it
    playback({ seek_fraction: Number(seek.value) / 1000 });
  };
  rate.onchange = () => playback({ rate: Number(rate.value) });
  loop.onchange = () => playback({ loop: loop.checked });
  const replays = model.get("replays") || [];
  if (replays.length) { timeline.hidden = false; timeline.dataset.sources = replays.join(","); playback({}); }
  const poll = setInterval(() => { if (!timeline.hidden && !pbWaiting) playback({}); }, 1000);

  // ------------------------------------------------------------------ messages from the kernel
  const onMsg = (msg, buffers) => {
    if (msg.type === "frame") onFrame(msg, buffers[0]);
    else if (msg.type === "reply") onState(msg);
    else if (msg.type === "pick") showPick(msg);
    else if (msg.type === "legend") drawLegend(msg.legend);  // the data changed after the last frame
    else if (msg.type === "playback") { pbWaiting = Math.max(0, pbWaiting - 1); onPlayback(msg); }
    else if (msg.type === "error") {
      if (String(msg.key || "").startsWith("playback")) pbWaiting = Math.max(0, pbWaiting - 1);
      info.textContent = `refused: ${msg.key ? msg.key + ": " : ""}${msg.error}`; info.hidden = false;
    } else if (msg.type === "stats" && !stopped()) {
      const src = msg.sources || [];
      stats.textContent = [`points ${msg.points}`, `render ${msg.fps} fps`, `view ${msg.view_fps} fps`,
        `${Math.round((msg.bytes_per_frame || 0) / 1024)} KB/frame`, `encode ${msg.encode_ms} ms`,
        `${src.length === 1 ? "source" : "sources"}: ${src.join(", ") || "–"}`].join(" · ");
    }
  };
  model.on("msg:custom", onMsg);

  // ------------------------------------------------------------------ the run ended
  function onStopped() {
    const why = model.get("stopped");
    root.classList.toggle("pf-stopped", !!why);
    for (const c of root.querySelectorAll("button, select, input")) c.disabled = !!why;
    ended.hidden = !why;
    if (!why) return;
    ended.textContent = why;
    canvas.dataset.stopped = why;
    stats.textContent = `${why} — the picture is the last frame drawn`;
    clearInterval(poll);
  }
  model.on("change:stopped", onStopped);
  onStopped();

  // ------------------------------------------------------------------ controls
  fit.onclick = () => control({ cmd: "fit" });
  reset.onclick = () => {
    control({ cmd: "fit" });
    if (state0) {
      const st = state0.style;
      control({ cmd: "style", color_by: st.color_by, colormap: st.colormap, color_range: st.color_range,
                point_size: st.point_size, edl: st.edl });
    }
  };
  mode.onchange = () => { clearMarks(); info.hidden = true; };
  colorBy.onchange = () => control({ cmd: "style", color_by: colorBy.value });
  cmap.onchange = () => control({ cmd: "style", colormap: cmap.value });
  size.oninput = () => { sizeVal.textContent = `${size.value} px`; };
  size.onchange = () => control({ cmd: "style", point_size: Number(size.value) });
  edl.onchange = () => control({ cmd: "style", edl: edl.checked });
  helpBtn.onclick = () => { help.hidden = !help.hidden; };

  // drags, wheel, pinch and keys: the page's gestures.js, prepended to this module by widget.py
  pointflowGestures(canvas, control, (x, y) => { pickAt = [x, y]; send({ type: "pick", x, y }); }, (e) => {
    if (stopped()) return false;
    if (e.key === "f") fit.click();
    else if (e.key === "r") reset.click();
    else if (e.key === "?") helpBtn.click();
    else if (e.key === " " && !timeline.hidden) play.click();
    else if ({ a: "axes", g: "grid", c: "compass", l: "legend" }[e.key] && !showBox.hidden) toggle({ a: "axes", g: "grid", c: "compass", l: "legend" }[e.key]);
    else return false;
    return true;
  });

  send({ type: "hello" });
  return () => { alive = false; clearInterval(poll); model.off("msg:custom", onMsg); model.off("change:stopped", onStopped); };
}

export default { render };
