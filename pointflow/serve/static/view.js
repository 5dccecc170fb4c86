// pointflow view: the live frame of one view, steered by the control messages of
// render/control.py over one WebSocket (docs/views.md). Frames arrive as binary messages
// [u32 header length][JSON header][JPEG or PNG]; each one drawn is acknowledged ("ack"),
// which lets the server send the next (at most two in flight).
"use strict";
(function () {
  const $ = (id) => document.getElementById(id);
  const canvas = $("view"), g = canvas.getContext("2d"), statusEl = $("status"), info = $("info");
  let ws = null, req = 1, frame = { width: 0, height: 0 }, hello = null, state0 = null;
  let lastState = null, drawing = Promise.resolve(), measureA = null, pendingPicks = new Map();
  let shown = 0, shownT = [], playbackState = null, seeking = false;
  window.pointflowView = { frames: () => shown, state: () => lastState, lastPick: null, playback: () => playbackState };

  function send(msg) { if (ws && ws.readyState === 1) ws.send(JSON.stringify(msg)); }
  function control(msg) { msg.req = req++; send(msg); return msg.req; }
  window.pointflowView.control = control;

  function viewSize() {
    const r = canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    return { width: Math.max(16, Math.min(4096, Math.round(r.width * dpr))),
             height: Math.max(16, Math.min(4096, Math.round(r.height * dpr))) };
  }

  function connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    ws = new WebSocket(`${proto}//${location.host}/ws`);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { statusEl.textContent = "waiting for the first frame…"; };
    ws.onclose = (e) => {
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
      canvas.dataset.reduce = String(head.reduce || 1);  // > 1: sent smaller for a slow link
    }).catch(() => {}).then(() => send({ cmd: "ack" }));
  }

  function fmt(v) { return typeof v === "number" ? (Math.abs(v) >= 1e4 || (v !== 0 && Math.abs(v) < 1e-3) ? v.toExponential(3) : v.toFixed(3)) : String(v); }

  function showPick(p, source) {
    if (!p) { info.textContent = "no point there"; info.hidden = false; return; }
    const pos = p.position || [];
    let text = `x ${fmt(pos[0])}\ny ${fmt(pos[1])}\nz ${fmt(pos[2])}`;
    if (source) text += `\nsource ${source}`;
    for (const [k, v] of Object.entries(p.channels || {})) text += `\n${k} ${fmt(v)}`;
    if ($("mode").value === "measure") {
      if (!measureA) { measureA = pos; text = "measure: first point\n" + text + "\n(click the second)"; }
      else {
        const d = Math.hypot(pos[0] - measureA[0], pos[1] - measureA[1], pos[2] - measureA[2]);
        text = `distance ${fmt(d)}\nfrom ${measureA.map(fmt).join(", ")}\nto   ${pos.map(fmt).join(", ")}`;
        measureA = null;
        canvas.dataset.distance = String(d);
      }
    }
    info.textContent = text; info.hidden = false;
    info.dataset.position = JSON.stringify(pos);
  }

  function fillOptions(sel, names, value) {
    sel.innerHTML = "";
    for (const n of names) { const o = document.createElement("option"); o.value = o.textContent = n; sel.appendChild(o); }
    if (value != null) sel.value = value;
  }

  function applyState(s) {
    lastState = s;
    if (!s || !s.style) return;
    if (!state0) state0 = s;
    const st = s.style;
    const cb = st.color_by == null ? "none" : st.color_by;
    if (hello && ![...$("color_by").options].some((o) => o.value === cb)) fillOptions($("color_by"), [...hello.color_by, cb], cb);
    $("color_by").value = cb; $("colormap").value = st.colormap;
    $("point_size").value = st.point_size; $("edl").checked = !!st.edl;
    $("follow").value = (s.camera && s.camera.follow) || "";
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
      const cb = pendingPicks.get(m.req); pendingPicks.delete(m.req);
      window.pointflowView.lastPick = m; showPick(m.point, m.source);
    } else if (m.type === "error") {
      if (m.key === "playback") return;  // the once-a-second timeline poll while a request waits
      info.textContent = `refused: ${m.key ? m.key + ": " : ""}${m.error}`; info.hidden = false;
    }
    else if (m.type === "stats") { showStats(m); }
    else if (m.type === "playback") { onPlayback(m); }
  }

  function showStats(m) {
    const v = m.view || {};
    const parts = [`points ${m.points ?? "–"}`, `render ${m.fps ?? "–"} fps`, `view ${v.fps ?? 0} fps`,
      `drops ${v.drops ?? 0}`, `${Math.round((v.bytes_per_frame || 0) / 1024)} KB/frame`, `encode ${v.encode_ms ?? 0} ms`];
    if (m.sources) parts.push(`sources ${Array.isArray(m.sources) ? m.sources.join(", ") : JSON.stringify(m.sources)}`);
    $("stats").textContent = parts.join(" · ");
  }

  // ---------------------------------------------------------------- timeline
  function playback(args) { control({ cmd: "playback", ...args }); }
  function onPlayback(m) {
    const states = Object.values(m.sources || {}).map((r) => r.state).filter(Boolean);
    if (!states.length) return;
    const s = states[0]; playbackState = s;
    $("play").textContent = s.paused ? "Play" : "Pause";
    $("loop").checked = !!s.loop;
    $("position").textContent = `${s.position_s.toFixed(1)}${s.duration_s ? " / " + s.duration_s.toFixed(1) : ""} s`;
    if (!seeking && s.duration_s) $("seek").value = String(Math.round(1000 * s.position_s / s.duration_s));
    $("timeline").dataset.paused = String(s.paused);
  }
  $("play").onclick = () => playback({ paused: !(playbackState && playbackState.paused) });
  $("seek").oninput = () => { seeking = true; };
  $("seek").onchange = () => { seeking = false; playback({ seek_fraction: Number($("seek").value) / 1000 }); };
  $("rate").onchange = () => playback({ rate: Number($("rate").value) });
  $("loop").onchange = () => playback({ loop: $("loop").checked });
  setInterval(() => { if (!$("timeline").hidden) playback({}); }, 1000);

  // ---------------------------------------------------------------- controls
  $("fit").onclick = () => control({ cmd: "fit" });
  $("reset").onclick = () => {
    control({ cmd: "fit" });
    if (state0) control({ cmd: "style", ...state0.style });
  };
  $("color_by").onchange = () => control({ cmd: "style", color_by: $("color_by").value });
  $("colormap").onchange = () => control({ cmd: "style", colormap: $("colormap").value });
  $("point_size").onchange = () => control({ cmd: "style", point_size: Number($("point_size").value) });
  $("edl").onchange = () => control({ cmd: "style", edl: $("edl").checked });
  $("follow").onchange = () => control({ cmd: "follow", frame: $("follow").value.trim() || null });

  // drags, wheel, pinch and keys: gestures.js (shared with the notebook widget)
  pointflowGestures(canvas, control, (x, y) => { pendingPicks.set(control({ cmd: "pick", x, y }), true); }, (e) => {
    if (e.key === "f") $("fit").click();
    else if (e.key === "r") $("reset").click();
    else if (e.key === " " && !$("timeline").hidden) $("play").click();
    else return false;
    return true;
  });

  let resizeTimer = null;
  window.addEventListener("resize", () => {
    clearTimeout(resizeTimer);
    resizeTimer = setTimeout(() => send({ cmd: "resize", ...viewSize() }), 150);
  });
  connect();
})();
