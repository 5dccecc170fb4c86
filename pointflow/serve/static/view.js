// pointflow view: the live frame of one view, steered by the control messages of
// render/view/protocol.py over one WebSocket (docs/views.md). Frames arrive as binary messages
// [u32 header length][JSON header][JPEG or PNG]; each one drawn is acknowledged ("ack"),
// which lets the server send the next (at most two in flight). Each header carries the
// camera the picture was drawn with and its colour legend: overlay.js draws axes, grid,
// compass, pick and measure marks from that camera; the legend bar uses the render stage's
// own colormap tables (the hello message's "luts").
"use strict";
(function () {
  const $ = (id) => document.getElementById(id);
  const canvas = $("view"), g = canvas.getContext("2d"), statusEl = $("status"), info = $("info");
  const over = $("overlay"), og = over.getContext("2d");
  let ws = null, req = 1, frame = { width: 0, height: 0 }, hello = null, state0 = null, ended = false;
  let lastState = null, drawing = Promise.resolve(), measureA = null, pendingPicks = new Map(), followSaid = "";
  let shown = 0, shownT = [], playbackState = null, seeking = false, seekHold = null;
  const marks = { pick: null, measure: [] };
  const show = { axes: true, grid: true, compass: true, legend: true };
  let overlayLayout = null;
  window.pointflowView = { frames: () => shown, state: () => lastState, lastPick: null, playback: () => playbackState,
                           camera: () => frame.camera || null, legend: () => frame.legend || null, units: () => frame.units || null,
                           overlay: () => overlayLayout, marks: () => marks, ended: () => ended };

  function send(msg) { if (ws && ws.readyState === 1) ws.send(JSON.stringify(msg)); }
  function control(msg) { msg.req = req++; send(msg); return msg.req; }
  window.pointflowView.control = control;
  window.pointflowView.fmtFull = fmtFull;  // (tests: how a picked value is shown)

  function viewSize() {
    const r = canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    return { width: Math.max(16, Math.min(4096, Math.round(r.width * dpr))),
             height: Math.max(16, Math.min(4096, Math.round(r.height * dpr))) };
  }

  // ---------------------------------------------------------------- connection
  const RUN_ENDED = 4000;  // serve/server.py CLOSE_RUN_ENDED: the pipeline stopped its view server
  function connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    ws = new WebSocket(`${proto}//${location.host}/ws`);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { statusEl.textContent = "waiting for the first frame…"; };
    ws.onclose = (e) => {
      if (e.code === RUN_ENDED) {  // the run is over: nothing will come back, stop retrying
        ended = true;
        statusEl.textContent = "run ended"; statusEl.className = "ended";
        $("stats").textContent = "run ended — the last picture stays; start the pipeline again and reload";
        document.body.dataset.ended = "true";
        return;
      }
      // the view server restarted or the link dropped: try again; a refusal (bad message) stays closed
      const again = ![1003, 1008, 1009, 1011].includes(e.code);  // 1011: the server failed on a message of ours
      statusEl.textContent = `disconnected (${e.code}${e.reason ? ": " + e.reason : ""})` + (again ? " — reconnecting…" : " — reload to reconnect");
      if (again) setTimeout(connect, 1000);
    };
    ws.onmessage = (e) => {
      if (typeof e.data === "string") onJson(JSON.parse(e.data)); else onFrame(e.data);
    };
  }

  function onFrame(buf) {
    const n = new DataView(buf).getUint32(0);
    const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
    const blob = new Blob([new Uint8Array(buf, 4 + n)], { type: head.mime });
    drawing = drawing.then(() => createImageBitmap(blob)).then((bmp) => {
      // a frame reduced for a slow link (head.reduce > 1) is drawn at the view's size
      const w = head.width || bmp.width, h = head.height || bmp.height;
      if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
      g.drawImage(bmp, 0, 0, w, h);
      bmp.close();
      frame = head; shown++;
      const now = performance.now(); shownT.push(now); while (shownT.length && now - shownT[0] > 2000) shownT.shift();
      statusEl.textContent = "";
      canvas.dataset.frames = String(shown);
      canvas.dataset.mime = head.mime;
      drawOverlay();
      drawLegend(head.legend);
      canvas.dataset.reduce = String(head.reduce || 1);  // > 1: sent smaller for a slow link
    }).catch(() => {}).then(() => send({ cmd: "ack" }));
  }

  // ---------------------------------------------------------------- overlay and legend
  function drawOverlay() {
    if (over.width !== canvas.width || over.height !== canvas.height) { over.width = canvas.width; over.height = canvas.height; }
    overlayLayout = pointflowOverlay.draw(og, frame.camera, over.width, over.height,
      { axes: show.axes, grid: show.grid, compass: show.compass, marks, follow: frame.follow, units: frame.units });
    over.dataset.drawn = String(shown);
  }

  function lutRgb(name) {
    return pointflowOverlay.decodeLut(hello && hello.luts && hello.luts[name]);
  }
  const lutCache = {};
  let legendKey = "";
  function drawLegend(lg) {
    const el = $("legend");
    const lut = lg && (lutCache[lg.colormap] || (lutCache[lg.colormap] = lutRgb(lg.colormap)));
    if (!show.legend || !lg || !lut || lg.range[0] == null || lg.range[1] == null) { el.hidden = true; return; }
    el.hidden = false;
    const [lo, hi] = lg.range, key = JSON.stringify(lg);
    if (key === legendKey) return;
    legendKey = key;
    el.dataset.lo = String(lo); el.dataset.hi = String(hi); el.dataset.colormap = lg.colormap;
    $("legend_title").textContent = pointflowOverlay.legendTitle(lg);
    const bar = $("legend_bar"), bg = bar.getContext("2d");
    bg.putImageData(new ImageData(lut, 256, 1), 0, 0);
    const ticks = $("legend_ticks");
    ticks.innerHTML = "";
    const put = (cls, v, frac) => {
      const s = document.createElement("span");
      s.className = cls; s.textContent = pointflowOverlay.fmtTick(v, hi - lo);
      if (cls === "mid") s.style.left = `${100 * frac}%`;
      ticks.appendChild(s);
      const t = document.createElement("i"); t.style.left = `${Math.min(99.5, 100 * frac)}%`; ticks.appendChild(t);
    };
    put("lo", lo, 0); put("hi", hi, 1);
    if (hi > lo) {  // round values between, where their labels do not run into the ends'
      const step = pointflowOverlay.niceStep((hi - lo) / 4);
      for (let v = Math.ceil(lo / step) * step; v < hi; v += step) {
        const f = (v - lo) / (hi - lo);
        if (f > 0.25 && f < 0.75) put("mid", +v.toPrecision(6), f);
      }
    }
  }

  function readHash() {
    const h = new URLSearchParams(location.hash.replace(/^#/, ""));
    for (const k of Object.keys(show)) if (h.has(k)) show[k] = !["0", "false", "off", "no"].includes(h.get(k));
    for (const k of Object.keys(show)) $(`show_${k}`).checked = show[k];
  }
  function writeHash() {
    const h = new URLSearchParams();
    for (const k of Object.keys(show)) if (!show[k]) h.set(k, "0");
    const s = h.toString();
    history.replaceState(null, "", s ? `#${s}` : location.pathname + location.search);
  }
  function toggle(k, on) {
    show[k] = on === undefined ? !show[k] : on;
    $(`show_${k}`).checked = show[k];
    writeHash(); drawOverlay(); drawLegend(frame.legend);
  }
  for (const k of Object.keys(show)) $(`show_${k}`).onchange = () => toggle(k, $(`show_${k}`).checked);
  window.addEventListener("hashchange", () => { readHash(); drawOverlay(); drawLegend(frame.legend); });
  readHash();

  // ---------------------------------------------------------------- pick and measure
  function fmt(v) { return typeof v === "number" ? (Math.abs(v) >= 1e4 || (v !== 0 && Math.abs(v) < 1e-3) ? v.toExponential(3) : v.toFixed(3)) : String(v); }
  function fmtFull(v) { return pointflowOverlay.fmtFull(v); }  // (overlay.js: both views show picks alike)

  function clearMarks() {
    marks.pick = null; marks.measure = []; measureA = null;
    info.hidden = true; info.textContent = "";
    delete canvas.dataset.distance;
    drawOverlay();
  }

  function showPick(p, source) {
    if (!p) { info.textContent = "no point there"; info.hidden = false; marks.pick = null; drawOverlay(); return; }
    const pos = p.position || [];
    let text = `x ${fmtFull(pos[0])}\ny ${fmtFull(pos[1])}\nz ${fmtFull(pos[2])}`;
    if (source) text += `\nsource: ${source}`;
    for (const [k, v] of Object.entries(p.channels || {})) if (k !== "source_index") text += `\n${k} ${fmtFull(v)}`;
    if ($("mode").value === "measure") {
      marks.pick = null;
      if (!measureA) { measureA = pos; marks.measure = [pos]; text = "measure: first point\n" + text + "\n(click the second)"; }
      else {
        const d = Math.hypot(pos[0] - measureA[0], pos[1] - measureA[1], pos[2] - measureA[2]);
        text = `distance ${pointflowOverlay.fmtDistance(d, frame.units)}\nfrom ${measureA.map(fmtFull).join(", ")}\nto   ${pos.map(fmtFull).join(", ")}`;
        marks.measure = [measureA, pos];
        measureA = null;
        canvas.dataset.distance = String(d);
      }
    } else { marks.pick = pos; marks.measure = []; }
    info.textContent = text; info.hidden = false;
    info.dataset.position = JSON.stringify(pos);
    drawOverlay();
  }

  // ---------------------------------------------------------------- state
  function fillOptions(sel, names, value) {
    sel.innerHTML = "";
    for (const n of names) { const o = document.createElement("option"); o.value = o.textContent = n; sel.appendChild(o); }
    if (value != null) sel.value = value;
  }

  function applyState(s) {
    const before = lastState && lastState.style;
    lastState = s;
    if (!s || !s.style) return;
    if (!state0) state0 = s;
    const st = s.style;
    const cb = st.color_by == null ? "none" : st.color_by;
    if (hello && ![...$("color_by").options].some((o) => o.value === cb)) fillOptions($("color_by"), [...hello.color_by, cb], cb);
    $("color_by").value = cb; $("colormap").value = st.colormap;
    $("point_size").value = st.point_size; $("point_size_value").textContent = String(st.point_size);
    $("edl").checked = !!st.edl;
    $("follow").value = (s.camera && s.camera.follow) || "";
    // a frame followed but not known (a typo, or its transforms not come yet): said, not silent
    const fs = s.follow_status || "";
    $("follow").title = fs ? `follow: ${fs}` : "a frame for the camera to follow (frames.fixed)";
    $("follow").dataset.status = fs;
    if (fs && fs !== "following" && fs !== followSaid) { info.textContent = `follow ${s.camera.follow}: ${fs}`; info.hidden = false; }
    followSaid = fs;
    // a pick's channel values belong to the colouring shown: a new colouring clears the panel
    if (before && (before.color_by !== st.color_by) && (marks.pick || marks.measure.length)) clearMarks();
  }

  function onJson(m) {
    if (m.type === "hello") {
      hello = m;
      fillOptions($("color_by"), m.color_by || ["z"]);
      fillOptions($("colormap"), m.colormaps || ["turbo"]);
      send({ cmd: "resize", ...viewSize() });
      const c = lastState && lastState.camera;  // a reconnect keeps the camera the user had
      if (c && c.mode === "fixed" && c.eye && c.target) control({ cmd: "camera", eye: c.eye, target: c.target, up: c.up, fov_deg: c.fov_deg });
      control({ cmd: "view_state" });
      if (m.replays && m.replays.length) { $("timeline").hidden = false; playback({}); }
    } else if (m.type === "reply") { applyState(m.state || m); }
    else if (m.type === "pick") {
      pendingPicks.delete(m.req);
      window.pointflowView.lastPick = m; showPick(m.point, m.source);
    } else if (m.type === "error") {
      if (m.key === "playback") return;  // the once-a-second timeline poll while a request waits
      // the error text of a ControlError already starts with its key: say the key once
      const e = String(m.error || ""), k = m.key ? String(m.key) : "";
      info.textContent = `refused: ${k && !e.startsWith(k + ":") ? k + ": " : ""}${e}`; info.hidden = false;
    }
    else if (m.type === "stats") { showStats(m); }
    else if (m.type === "legend") { frame.legend = m.legend; drawLegend(m.legend); }  // the data changed after the last frame
    else if (m.type === "playback") { onPlayback(m); }
  }

  const DROPS_TIP = "frames this view skipped: a newer frame replaced one still waiting for this page " +
    "(a slow link or a busy browser); the newest picture is always the one shown";
  function showStats(m) {
    if (ended) return;
    const v = m.view || {};
    const el = $("stats");
    el.textContent = "";
    const part = (text, tip) => {
      if (el.childNodes.length) el.appendChild(document.createTextNode(" · "));
      const s = document.createElement("span"); s.textContent = text; if (tip) s.title = tip; el.appendChild(s);
    };
    part(`points ${m.points ?? "–"}`, "points held in the ring (what the picture draws from)");
    part(`render ${m.fps ?? "–"} fps`, "pictures the render stage drew per second (all views)");
    part(`view ${v.fps ?? 0} fps`, "frames this page received per second");
    part(`drops ${v.drops ?? 0}`, DROPS_TIP);
    part(`${Math.round((v.bytes_per_frame || 0) / 1024)} KB/frame`);
    part(`encode ${v.encode_ms ?? 0} ms`, "time to compress one frame (JPEG while moving, PNG when still)");
    if (m.sources) {
      const names = Array.isArray(m.sources) ? m.sources : Object.keys(m.sources);
      part(`${names.length === 1 ? "source" : "sources"}: ${names.join(", ")}`);
    }
  }

  // ---------------------------------------------------------------- timeline
  function playback(args) { control({ cmd: "playback", ...args }); }
  function onPlayback(m) {
    const states = Object.values(m.sources || {}).map((r) => r.state || r).filter((s) => s && s.position_s != null);
    if (!states.length) return;
    const s = states[0]; playbackState = s;
    $("play").textContent = s.paused ? "Play" : "Pause";
    $("loop").checked = !!s.loop;
    $("position").textContent = `${s.position_s.toFixed(1)}${s.duration_s ? " / " + s.duration_s.toFixed(1) : ""} s`;
    // a seek holds the slider where the user left it until the replay has landed there
    if (seekHold && (performance.now() > seekHold.until || (s.seeks > seekHold.seeks && !s.seek_pending && s.index !== seekHold.index))) seekHold = null;
    if (!seeking && !seekHold && s.duration_s) $("seek").value = String(Math.round(1000 * s.position_s / s.duration_s));
    $("timeline").dataset.paused = String(s.paused);
    $("timeline").dataset.index = String(s.index);
  }
  $("play").onclick = () => playback({ paused: !(playbackState && playbackState.paused) });
  $("step").onclick = () => playback({ step: 1 });
  $("seek").oninput = () => { seeking = true; };
  $("seek").onchange = () => {
    seeking = false;
    const s = playbackState || {};
    seekHold = { seeks: s.seeks || 0, index: s.index, until: performance.now() + 5000 };
    playback({ seek_fraction: Number($("seek").value) / 1000 });
  };
  $("rate").onchange = () => playback({ rate: Number($("rate").value) });
  $("loop").onchange = () => playback({ loop: $("loop").checked });
  setInterval(() => { if (!$("timeline").hidden && !ended) playback({}); }, 1000);

  // ---------------------------------------------------------------- controls
  $("fit").onclick = () => control({ cmd: "fit" });
  $("reset").onclick = () => {
    control({ cmd: "fit" });
    if (state0) control({ cmd: "style", ...state0.style });
  };
  $("mode").onchange = () => clearMarks();  // a pick's marker or half a measurement does not carry over
  $("color_by").onchange = () => control({ cmd: "style", color_by: $("color_by").value });
  $("colormap").onchange = () => control({ cmd: "style", colormap: $("colormap").value });
  $("point_size").oninput = () => { $("point_size_value").textContent = $("point_size").value; };
  $("point_size").onchange = () => control({ cmd: "style", point_size: Number($("point_size").value) });
  $("edl").onchange = () => control({ cmd: "style", edl: $("edl").checked });
  $("follow").onchange = () => control({ cmd: "follow", frame: $("follow").value.trim() || null });

  const help = $("help");
  const openHelp = (on) => { help.hidden = on === undefined ? !help.hidden : !on; };
  $("help_button").onclick = () => openHelp();
  $("help_close").onclick = () => openHelp(false);

  // drags, wheel, pinch and keys: gestures.js (shared with the notebook widget)
  pointflowGestures(canvas, control, (x, y) => { pendingPicks.set(control({ cmd: "pick", x, y }), true); }, (e) => {
    if (e.key === "f") $("fit").click();
    else if (e.key === "r") $("reset").click();
    else if (e.key === " " && !$("timeline").hidden) $("play").click();
    else return false;
    return true;
  });
  // the page's own keys, wherever the focus is but in a text field
  document.addEventListener("keydown", (e) => {
    const t = e.target;
    if (e.ctrlKey || e.metaKey || e.altKey || (t && (t.tagName === "INPUT" && t.type === "text" || t.tagName === "SELECT"))) return;
    if (e.key === "?") openHelp();
    else if (e.key === "Escape") { if (!help.hidden) openHelp(false); else clearMarks(); }
    else if (e.key === "." && !$("timeline").hidden) $("step").click();
    else if (e.key === "m") { $("mode").value = $("mode").value === "pick" ? "measure" : "pick"; clearMarks(); }
    else if (e.key === "a") toggle("axes");
    else if (e.key === "g") toggle("grid");
    else if (e.key === "c") toggle("compass");
    else if (e.key === "l") toggle("legend");
    else return;
    e.preventDefault();
  });

  let resizeTimer = null;
  const resized = () => {  // the window, or the stage when the bars around it wrap
    clearTimeout(resizeTimer);
    resizeTimer = setTimeout(() => send({ cmd: "resize", ...viewSize() }), 150);
  };
  window.addEventListener("resize", resized);
  if (window.ResizeObserver) new ResizeObserver(resized).observe($("stage"));
  connect();
})();
