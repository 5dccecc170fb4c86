// pointflow view overlay: orientation and annotations drawn on a 2D canvas over the view's
// picture, from the camera the render stage drew that picture with (each frame's header:
// eye, target, up, fov_deg, near, far; render/camera.py's look_at and perspective). No
// dependencies; loaded by the page (view.js) and loadable by the notebook widget.
//   pointflowOverlay.project(cam, w, h, p) -> [x, y, depth] in canvas pixels, or null behind the eye
//   pointflowOverlay.draw(g, cam, w, h, opts) draws; opts: {axes, grid, compass, marks: {pick, measure},
//     follow: {frame, origin}, units: {xy, z}} (the followed frame's axes, at half length, named;
//     units: the frame header's, the map's CRS or metres, for the grid and measure labels)
//   pointflowOverlay.niceStep(x) -> 1, 2 or 5 x 10^k nearest at or above x
//   pointflowOverlay.layout(cam) -> {spacing, axisLength} (what draw uses)
//   pointflowOverlay.fmtFull(v) -> a picked value as shown (3 decimals up to 1e12)
//   pointflowOverlay.fmtLen(x, unit) -> "200 m", "1.5 km", "200 ft" (unit "": none said)
//   pointflowOverlay.fmtDistance(d, units) -> a measure in full with its unit ("329.560 ft")
//   pointflowOverlay.legendTitle(legend) -> "z (ft) · turbo · auto range"
//   pointflowOverlay.fmtTick(v, range) -> a legend tick with the decimals the range needs
// Why an overlay and not pixels in the frame: crisp at any resolution and device pixel ratio,
// switched on and off without a new frame, and the same on every render tier.
"use strict";
var pointflowOverlay = (function () {
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => { const n = Math.hypot(a[0], a[1], a[2]); return n > 0 ? [a[0] / n, a[1] / n, a[2] / n] : a; };
  const AXIS = [["X", "#ff4040", [1, 0, 0]], ["Y", "#40e040", [0, 1, 0]], ["Z", "#4080ff", [0, 0, 1]]];

  // camera.py look_at: s (right), u (up), f (forward); eye space looks down -z
  function basis(cam) {
    const f = norm(sub(cam.target, cam.eye));
    let up = cam.up;
    if (Math.abs(dot(f, norm(up))) > 0.999) up = Math.abs(f[1]) < 0.9 ? [0, 1, 0] : [1, 0, 0];
    const s = norm(cross(f, up));
    return { s, u: cross(s, f), f };
  }

  function projector(cam, w, h) {
    const b = basis(cam), F = 1 / Math.tan((cam.fov_deg * Math.PI / 180) / 2), aspect = w / Math.max(h, 1);
    const near = Math.max(cam.near || 1e-6, 1e-9);
    const toEye = (p) => { const d = sub(p, cam.eye); return [dot(b.s, d), dot(b.u, d), dot(b.f, d)]; };  // depth = -z
    const toPx = (e) => [(F / aspect * e[0] / e[2] * 0.5 + 0.5) * w, (0.5 - F * e[1] / e[2] * 0.5) * h, e[2]];
    return { b, near, toEye, toPx, project: (p) => { const e = toEye(p); return e[2] > near ? toPx(e) : null; } };
  }

  function project(cam, w, h, p) { return projector(cam, w, h).project(p); }

  function niceStep(x) {
    if (!(x > 0) || !isFinite(x)) return 1;
    const k = Math.pow(10, Math.floor(Math.log10(x)));
    for (const m of [1, 2, 5, 10]) if (m * k >= x * (1 - 1e-9)) return m * k;
    return 10 * k;
  }

  function layout(cam) {
    const dist = Math.hypot(...sub(cam.eye, cam.target)) || 1;
    const spacing = niceStep(dist / 8);
    return { spacing, axisLength: 2 * spacing, dist };
  }

  // a picked value in full: georeferenced coordinates (6.4e5 ft) to the mm, not 4 digits
  function fmtFull(v) {
    if (typeof v !== "number" || !isFinite(v)) return String(v);
    if (v !== 0 && Math.abs(v) < 1e-3) return v.toExponential(6);
    return Math.abs(v) < 1e12 ? v.toFixed(3) : v.toExponential(9);
  }

  // a length in the view's unit (the frame's ``units.xy``: the map's CRS, else metres);
  // metres step to km / cm / mm, another unit is written as it is, "" means unknown
  function fmtLen(x, unit) {
    const a = Math.abs(x);
    if (unit != null && unit !== "m") return (+x.toPrecision(4)).toString() + (unit ? " " + unit : "");
    if (a >= 1000) return (x / 1000).toPrecision(3).replace(/\.?0+$/, "") + " km";
    if (a >= 1 || a === 0) return (+x.toPrecision(4)).toString() + " m";
    if (a >= 0.01) return (+(x * 100).toPrecision(3)).toString() + " cm";
    return (+(x * 1000).toPrecision(3)).toString() + " mm";
  }

  // a world segment clipped to the part in front of the near plane, in pixels (or null)
  function segment(P, a, b) {
    let ea = P.toEye(a), eb = P.toEye(b);
    const n = P.near * 1.0001;
    if (ea[2] <= n && eb[2] <= n) return null;
    if (ea[2] <= n || eb[2] <= n) {
      const t = (n - ea[2]) / (eb[2] - ea[2]);
      const c = [ea[0] + t * (eb[0] - ea[0]), ea[1] + t * (eb[1] - ea[1]), n];
      if (ea[2] <= n) ea = c; else eb = c;
    }
    return [P.toPx(ea), P.toPx(eb)];
  }

  function line(g, P, a, b, color, width) {
    const s = segment(P, a, b);
    if (!s) return null;
    g.strokeStyle = color; g.lineWidth = width;
    g.beginPath(); g.moveTo(s[0][0], s[0][1]); g.lineTo(s[1][0], s[1][1]); g.stroke();
    return s;
  }

  function label(g, text, x, y, color, scale) {
    g.font = `${Math.round(12 * scale)}px system-ui, sans-serif`;
    g.lineWidth = 3 * scale; g.strokeStyle = "rgba(0,0,0,0.85)"; g.strokeText(text, x, y);
    g.fillStyle = color; g.fillText(text, x, y);
  }

  function drawGrid(g, P, cam, L, scale) {
    const n = 10, sp = L.spacing;
    const cx = Math.round(cam.target[0] / sp) * sp, cy = Math.round(cam.target[1] / sp) * sp;
    g.save();
    for (let i = -n; i <= n; i++) {
      const major = Math.abs(Math.round((cx + i * sp) / sp)) % 5 === 0;
      const c = major ? "rgba(200,200,200,0.35)" : "rgba(200,200,200,0.18)";
      line(g, P, [cx + i * sp, cy - n * sp, 0], [cx + i * sp, cy + n * sp, 0], c, scale);
      const majorY = Math.abs(Math.round((cy + i * sp) / sp)) % 5 === 0;
      line(g, P, [cx - n * sp, cy + i * sp, 0], [cx + n * sp, cy + i * sp, 0],
           majorY ? "rgba(200,200,200,0.35)" : "rgba(200,200,200,0.18)", scale);
    }
    g.restore();
  }

  function drawAxes(g, P, L, scale, o, title) {
    o = o || [0, 0, 0];
    for (const [name, color, d] of AXIS) {
      const tip = [o[0] + d[0] * L.axisLength, o[1] + d[1] * L.axisLength, o[2] + d[2] * L.axisLength];
      const s = line(g, P, o, tip, color, 3 * scale);
      if (s) label(g, name, s[1][0] + 4 * scale, s[1][1] - 4 * scale, color, scale);
    }
    const q = title && P.project(o);
    if (q) label(g, title, q[0] + 6 * scale, q[1] + 14 * scale, "#ddd", scale);
  }

  // a small axis triad in the bottom-left corner: the world's X, Y (north) and Z (up) as
  // the camera sees them (rotation only), the nearer drawn last
  function drawCompass(g, P, w, h, scale) {
    const r = 28 * scale, cx = 14 * scale + r, cy = h - 14 * scale - r;
    g.save();
    g.fillStyle = "rgba(0,0,0,0.45)"; g.beginPath(); g.arc(cx, cy, r + 8 * scale, 0, 2 * Math.PI); g.fill();
    const items = AXIS.map(([name, color, d]) => ({
      name: name === "Y" ? "N" : (name === "Z" ? "up" : name), color,
      x: dot(P.b.s, d), y: dot(P.b.u, d), z: dot(P.b.f, d) }));
    items.sort((a, b) => b.z - a.z);  // farthest (pointing away) first
    for (const it of items) {
      g.strokeStyle = it.color; g.lineWidth = 2.5 * scale; g.globalAlpha = it.z > 0.2 ? 0.55 : 1;
      g.beginPath(); g.moveTo(cx, cy); g.lineTo(cx + it.x * r, cy - it.y * r); g.stroke();
      label(g, it.name, cx + it.x * (r + 2 * scale) - 4 * scale, cy - it.y * (r + 2 * scale) + 4 * scale, it.color, scale * 0.9);
    }
    g.restore();
  }

  function drawMarks(g, P, marks, scale, unit) {
    if (!marks) return;
    const ring = (p, color) => {
      const q = P.project(p);
      if (!q) return null;
      g.strokeStyle = "rgba(0,0,0,0.9)"; g.lineWidth = 4 * scale;
      g.beginPath(); g.arc(q[0], q[1], 7 * scale, 0, 2 * Math.PI); g.stroke();
      g.strokeStyle = color; g.lineWidth = 2 * scale;
      g.beginPath(); g.arc(q[0], q[1], 7 * scale, 0, 2 * Math.PI); g.stroke();
      return q;
    };
    if (marks.pick) ring(marks.pick, "#ffffff");
    const m = marks.measure || [];
    if (m.length === 2) {
      const s = segment(P, m[0], m[1]);
      if (s) {
        g.strokeStyle = "rgba(0,0,0,0.9)"; g.lineWidth = 5 * scale;
        g.beginPath(); g.moveTo(s[0][0], s[0][1]); g.lineTo(s[1][0], s[1][1]); g.stroke();
        g.strokeStyle = "#ffd23f"; g.lineWidth = 2.5 * scale;
        g.beginPath(); g.moveTo(s[0][0], s[0][1]); g.lineTo(s[1][0], s[1][1]); g.stroke();
        const d = Math.hypot(...sub(m[1], m[0]));
        label(g, fmtLen(d, unit), (s[0][0] + s[1][0]) / 2 + 8 * scale, (s[0][1] + s[1][1]) / 2 - 8 * scale, "#ffd23f", scale * 1.1);
      }
    }
    for (const p of m) ring(p, "#ffd23f");
  }

  function draw(g, cam, w, h, opts) {
    g.clearRect(0, 0, w, h);
    if (!cam || !cam.eye || !cam.target) return null;
    const P = projector(cam, w, h), L = layout(cam), scale = Math.max(1, Math.min(w, h) / 500);
    const unit = opts.units ? opts.units.xy : undefined;
    if (opts.grid) {
      drawGrid(g, P, cam, L, scale);
      label(g, `grid ${fmtLen(L.spacing, unit)}`, (opts.compass ? 90 : 10) * scale, h - 12 * scale, "#ccc", scale);
    }
    if (opts.axes) {
      drawAxes(g, P, L, scale);
      if (opts.follow && opts.follow.origin) drawAxes(g, P, { axisLength: L.axisLength / 2 }, scale, opts.follow.origin, opts.follow.frame);
    }
    drawMarks(g, P, opts.marks, scale, unit);
    if (opts.compass) drawCompass(g, P, w, h, scale);
    return L;
  }

  // a colormap's table as sent by the server / widget (``rrggbb`` x 256: render/view/legend.py
  // lut_hex) -> RGBA bytes for the legend bar; null when there is none
  function decodeLut(hex) {
    if (!hex) return null;
    const out = new Uint8ClampedArray(256 * 4);
    for (let i = 0; i < 256; i++) {
      for (let c = 0; c < 3; c++) out[4 * i + c] = parseInt(hex.substr(6 * i + 2 * c, 2), 16);
      out[4 * i + 3] = 255;
    }
    return out;
  }

  // a measured distance in full, with the frame's unit (units.xy; metres when the frame says none)
  function fmtDistance(d, units) {
    const u = units && units.xy != null ? units.xy : "m";
    return fmtFull(d) + (u ? " " + u : "");
  }

  // a legend tick: as many decimals as the range needs (a range of 114 gives 1: "406.3",
  // "450.0"), so the end and middle labels do not run into each other (3 decimals did)
  function fmtTick(v, range) {
    if (typeof v !== "number" || !isFinite(v)) return String(v);
    if (Math.abs(v) >= 1e6 || (v !== 0 && Math.abs(v) < 1e-3)) return v.toExponential(3);
    const d = range > 0 && isFinite(range) ? Math.min(3, Math.max(0, 3 - Math.floor(Math.log10(range)))) : 3;
    return v.toFixed(d);
  }

  // the colour legend's title: the channel, its unit for heights (the frame's legend.unit)
  function legendTitle(lg) {
    const z = lg.color_by === "z" || lg.color_by === "height";
    const unit = lg.unit != null ? lg.unit : (z ? "m" : "");
    return `${lg.color_by}${unit ? ` (${unit})` : ""} · ${lg.colormap}${lg.auto ? " · auto range" : ""}`;
  }

  return { project, draw, niceStep, layout, fmtLen, fmtFull, fmtDistance, fmtTick, decodeLut, legendTitle };
})();
if (typeof module !== "undefined") module.exports = pointflowOverlay;
