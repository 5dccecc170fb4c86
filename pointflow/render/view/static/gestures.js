// pointflow view gestures, shared by the page (view.js) and the notebook widget
// (pointflow/notebook/static/widget.js, which the widget's Python prepends this file to):
// a drag orbits (right button or shift: pans), the wheel and a two-finger pinch zoom, two
// fingers moving pan, arrows orbit (shift: pan), +/- zoom, a click without a drag picks.
// Moves are summed and sent as view control messages at most once per animation frame, so a
// client's message rate stays far below the server's limit.
//   control(msg): send one control message;  onPick(x, y): a click at canvas pixel (x, y);
//   onKey(e): the caller's own keys (true when it took the key).
function pointflowGestures(canvas, control, onPick, onKey) {
  const ORBIT_DEG_PER_PX = 0.4, ZOOM_PER_NOTCH = 1.15, KEY_STEP_PX = 20;
  let acc = { orbit: [0, 0], pan: [0, 0], zoom: 0 }, scheduled = false;
  function flush() {
    scheduled = false;
    const h = Math.max(1, canvas.getBoundingClientRect().height);
    if (acc.orbit[0] || acc.orbit[1]) control({ cmd: "orbit", azimuth_deg: -acc.orbit[0] * ORBIT_DEG_PER_PX, elevation_deg: acc.orbit[1] * ORBIT_DEG_PER_PX });
    if (acc.pan[0] || acc.pan[1]) control({ cmd: "pan", right: -acc.pan[0] / h, up: acc.pan[1] / h });
    if (acc.zoom) control({ cmd: "zoom", factor: Math.pow(ZOOM_PER_NOTCH, acc.zoom) });
    acc = { orbit: [0, 0], pan: [0, 0], zoom: 0 };
  }
  function later() { if (!scheduled) { scheduled = true; requestAnimationFrame(flush); } }

  const touches = new Map();
  let drag = null, pinch = null;
  canvas.addEventListener("pointerdown", (e) => {
    if (e.pointerType === "touch") touches.set(e.pointerId, [e.clientX, e.clientY]);
    canvas.setPointerCapture(e.pointerId); canvas.focus();
    drag = { x: e.clientX, y: e.clientY, x0: e.clientX, y0: e.clientY, moved: false,
             pan: e.button === 2 || e.shiftKey, id: e.pointerId };
  });
  canvas.addEventListener("pointermove", (e) => {
    if (drag && e.pointerId === drag.id && touches.size <= 1) {
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      if (Math.hypot(e.clientX - drag.x0, e.clientY - drag.y0) > 4) drag.moved = true;
      if (drag.moved) { const k = drag.pan ? acc.pan : acc.orbit; k[0] += dx; k[1] += dy; later(); }
    }
    if (e.pointerType !== "touch" || !touches.has(e.pointerId)) return;
    touches.set(e.pointerId, [e.clientX, e.clientY]);
    if (touches.size !== 2) { pinch = null; return; }
    const [a, b] = [...touches.values()];
    const d = Math.hypot(a[0] - b[0], a[1] - b[1]), c = [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2];
    if (pinch) {
      if (pinch.d > 0 && d > 0) acc.zoom += Math.log(d / pinch.d) / Math.log(ZOOM_PER_NOTCH);
      acc.pan[0] += c[0] - pinch.c[0]; acc.pan[1] += c[1] - pinch.c[1]; later();
    }
    pinch = { d, c };
  });
  const release = (e) => {
    if (e.type === "pointerup" && drag && e.pointerId === drag.id && !drag.moved && e.button === 0 && touches.size <= 1) {
      const r = canvas.getBoundingClientRect();
      onPick((e.clientX - r.left) * (canvas.width / r.width), (e.clientY - r.top) * (canvas.height / r.height));
    }
    if (e.type === "pointerup") drag = null;
    touches.delete(e.pointerId); pinch = null;
  };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); acc.zoom += e.deltaY < 0 ? 1 : -1; later(); }, { passive: false });
  canvas.addEventListener("keydown", (e) => {
    const s = KEY_STEP_PX;
    const k = { ArrowLeft: [-s, 0], ArrowRight: [s, 0], ArrowUp: [0, -s], ArrowDown: [0, s] }[e.key];
    if (k) { const t = e.shiftKey ? acc.pan : acc.orbit; t[0] += k[0]; t[1] += k[1]; later(); }
    else if (e.key === "+" || e.key === "=") { acc.zoom += 1; later(); }
    else if (e.key === "-") { acc.zoom -= 1; later(); }
    else if (!onKey(e)) return;
    e.preventDefault(); e.stopPropagation();  // a notebook's own shortcuts stay out of it
  });
}
