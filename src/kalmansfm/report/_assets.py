"""Inline CSS and JavaScript of the HTML report (no libraries, no network).

The script is plain ES2017 that every current browser runs from a local file.
It drives the frame player, the drag-to-rotate 3D view and the sortable
tables, and finally writes ``data-ready="yes"`` on ``#js-status`` so that a
headless browser test can tell that it ran; uncaught errors are recorded on
the same element (``data-errors``).
"""

CSS = """
:root { --ink:#1d2327; --muted:#5f6b73; --line:#d8dee3; --accent:#1f77b4; --bg:#f6f8fa; }
* { box-sizing: border-box; }
body { margin:0; font:15px/1.5 system-ui,-apple-system,"Segoe UI",Roboto,"Helvetica Neue",Arial,sans-serif;
       color:var(--ink); background:#fff; }
header { background:var(--bg); border-bottom:1px solid var(--line); padding:18px 0 10px; }
.wrap { max-width:1120px; margin:0 auto; padding:0 20px; }
h1 { font-size:24px; margin:0 0 4px; }
h2 { font-size:20px; margin:0 0 10px; padding-top:8px; }
h3 { font-size:16px; margin:18px 0 6px; }
.meta { color:var(--muted); font-size:13px; margin:0; }
.meta code { font-size:12px; }
nav { position:sticky; top:0; z-index:5; background:#fff; border-bottom:1px solid var(--line); }
nav .wrap { display:flex; flex-wrap:wrap; gap:4px 16px; padding-top:6px; padding-bottom:6px; font-size:14px; }
nav a { color:var(--accent); text-decoration:none; }
nav a:hover { text-decoration:underline; }
section { padding:18px 0 10px; border-bottom:1px solid var(--line); scroll-margin-top:44px; }
.cards { display:grid; grid-template-columns:repeat(auto-fill,minmax(150px,1fr)); gap:10px; margin:14px 0 6px; }
.card { background:#fff; border:1px solid var(--line); border-radius:6px; padding:8px 10px; }
.card .value { font-size:20px; font-weight:600; }
.card .label { font-size:12px; color:var(--muted); }
table { border-collapse:collapse; font-size:13px; margin:6px 0 12px; }
th, td { border-bottom:1px solid var(--line); padding:3px 10px; text-align:left; vertical-align:top; }
th { background:var(--bg); }
td.num { text-align:right; font-variant-numeric:tabular-nums; }
table.sortable th { cursor:pointer; }
table.sortable th:hover { text-decoration:underline; }
.swatch { display:inline-block; width:11px; height:11px; border-radius:2px; margin-right:6px; vertical-align:-1px; }
.two { display:grid; grid-template-columns:repeat(auto-fit,minmax(330px,1fr)); gap:18px; align-items:start; }
figure { margin:6px 0 14px; }
figure img { max-width:100%; height:auto; border:1px solid var(--line); background:#fff; }
figcaption { font-size:13px; color:var(--muted); margin-top:3px; }
.strip { display:grid; grid-template-columns:repeat(auto-fill,minmax(170px,1fr)); gap:8px; }
.strip figure { margin:0; }
.strip img { width:100%; image-rendering:pixelated; }
.player img { image-rendering:pixelated; max-width:100%; height:auto; }
.controls { display:flex; align-items:center; gap:8px; margin:6px 0; font-size:14px; flex-wrap:wrap; }
.controls input[type=range] { width:260px; }
button { font:inherit; font-size:13px; padding:2px 10px; border:1px solid var(--line); border-radius:4px;
         background:var(--bg); cursor:pointer; }
canvas.view3d { width:100%; max-width:720px; height:440px; border:1px solid var(--line); border-radius:4px;
                background:#fbfcfd; touch-action:none; cursor:grab; }
.warn { background:#fff6e0; border-left:4px solid #ff9f1c; padding:6px 10px; margin:6px 0; font-size:14px; }
.note { color:var(--muted); font-size:13px; }
footer { color:var(--muted); font-size:12px; padding:16px 0 30px; }
.legend span { margin-right:14px; font-size:13px; }
"""

JS = r"""
(function () {
  "use strict";
  var status = document.getElementById("js-status");

  function jsonData(id) {
    var node = document.getElementById(id);
    return node ? JSON.parse(node.textContent) : null;
  }

  // --- frame player -------------------------------------------------------
  function setupPlayer() {
    var frames = jsonData("player-frames");
    var img = document.getElementById("player-image");
    if (!frames || !img) { return; }
    var slider = document.getElementById("player-slider");
    var label = document.getElementById("player-label");
    var play = document.getElementById("player-play");
    var index = 0, timer = null;
    slider.max = String(frames.length - 1);
    function show(k) {
      index = (k + frames.length) % frames.length;
      img.src = frames[index].src;
      slider.value = String(index);
      label.textContent = "frame " + frames[index].frame + " (" + (index + 1) + " of " + frames.length + ")";
    }
    function stop() { if (timer) { clearInterval(timer); timer = null; play.textContent = "play"; } }
    play.addEventListener("click", function () {
      if (timer) { stop(); return; }
      timer = setInterval(function () { show(index + 1); }, 250);
      play.textContent = "pause";
    });
    document.getElementById("player-prev").addEventListener("click", function () { stop(); show(index - 1); });
    document.getElementById("player-next").addEventListener("click", function () { stop(); show(index + 1); });
    slider.addEventListener("input", function () { stop(); show(parseInt(slider.value, 10)); });
    show(0);
  }

  // --- 3D view ------------------------------------------------------------
  function mul(a, b) {
    var c = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
    for (var i = 0; i < 3; i++) for (var j = 0; j < 3; j++)
      for (var k = 0; k < 3; k++) c[i][j] += a[i][k] * b[k][j];
    return c;
  }
  function apply(m, p) {
    return [m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2],
            m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2],
            m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2]];
  }
  function rotX(a) { var c = Math.cos(a), s = Math.sin(a); return [[1, 0, 0], [0, c, -s], [0, s, c]]; }
  function rotY(a) { var c = Math.cos(a), s = Math.sin(a); return [[c, 0, s], [0, 1, 0], [-s, 0, c]]; }

  function setupView3d() {
    var data = jsonData("shape-data");
    var canvas = document.getElementById("view3d");
    if (!data || !canvas) { return; }
    var ctx = canvas.getContext("2d");
    var first = data.cameras && data.cameras.length ? data.cameras[0] : [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
    // start obliquely (first camera turned 35 degrees and tipped 20) so that depth is visible at once
    var start = mul(mul(rotX(-0.35), rotY(0.6)), first);
    var view = start, zoom = 1;
    var showTruth = document.getElementById("view3d-truth");
    var showUnreliable = document.getElementById("view3d-unreliable");
    var colourBy = document.getElementById("view3d-colour");
    // labels crowd a large cloud into a blob: drawn for small ones, else only for the point under the pointer
    var allLabels = data.points.length <= 60, hover = -1, drawn = [];
    var cameraSlider = document.getElementById("view3d-camera");
    var cameraLabel = document.getElementById("view3d-camera-label");

    function draw() {
      var ratio = window.devicePixelRatio || 1;
      var w = canvas.clientWidth, h = canvas.clientHeight;
      if (canvas.width !== Math.round(w * ratio)) { canvas.width = Math.round(w * ratio); }
      if (canvas.height !== Math.round(h * ratio)) { canvas.height = Math.round(h * ratio); }
      ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
      ctx.clearRect(0, 0, w, h);
      var s = zoom * 0.42 * Math.min(w, h) / data.radius;
      var cx = w / 2, cy = h / 2;
      var items = [];
      var palette = colourBy && colourBy.value === "uncertainty" && data.uncertainty_colors ? data.uncertainty_colors
        : data.colors;
      data.points.forEach(function (p, k) {
        var weak = data.unreliable && data.unreliable[k];
        if (weak && !(showUnreliable && showUnreliable.checked)) { return; }
        var q = apply(view, p);
        items.push({ q: q, kind: "point", color: palette[k], label: data.labels[k], weak: weak, index: k });
      });
      if (data.truth && (!showTruth || showTruth.checked)) {
        data.truth.forEach(function (p) { items.push({ q: apply(view, p), kind: "truth" }); });
      }
      // cameras: a dot on the side each camera looks from, joined by the path of the motion
      var camPath = [];
      (data.cameras || []).forEach(function (m, f) {
        var k = m[2], d = 1.6 * data.radius;
        // a perspective run knows where each camera stood; a factorization only where it looked from
        var q = data.camera_centres ? apply(view, data.camera_centres[f]) : apply(view, [-d * k[0], -d * k[1], -d * k[2]]);
        camPath.push(q);
        items.push({ q: q, kind: "camera", frame: data.camera_frames[f] });
      });
      if (camPath.length > 1) {
        ctx.strokeStyle = "rgba(148,103,189,0.5)"; ctx.lineWidth = 1; ctx.beginPath();
        camPath.forEach(function (q, f) {
          if (f === 0) { ctx.moveTo(cx + s * q[0], cy + s * q[1]); } else { ctx.lineTo(cx + s * q[0], cy + s * q[1]); }
        });
        ctx.stroke();
      }
      items.sort(function (a, b) { return b.q[2] - a.q[2]; });  // far first
      var depthSpan = 2 * 1.6 * data.radius;
      drawn = [];
      items.forEach(function (it) {
        var x = cx + s * it.q[0], y = cy + s * it.q[1];
        if (it.kind === "point") { drawn.push([x, y, it.index]); }
        var labelled = it.kind === "point" && (allLabels || it.index === hover);
        var near = 1 - (it.q[2] / depthSpan);  // bigger when closer to the viewer
        ctx.beginPath();
        if (it.kind === "point" && it.weak) {
          ctx.strokeStyle = it.color; ctx.lineWidth = 2;
          ctx.arc(x, y, Math.max(2.5, 5 * near), 0, 2 * Math.PI); ctx.stroke();
          if (labelled) { ctx.fillStyle = "#888"; ctx.font = "11px sans-serif"; ctx.fillText(String(it.label), x + 7, y - 5); }
        } else if (it.kind === "point") {
          ctx.fillStyle = it.color; ctx.strokeStyle = "#222"; ctx.lineWidth = 1;
          ctx.arc(x, y, Math.max(2.5, 5 * near), 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
          if (labelled) { ctx.fillStyle = "#333"; ctx.font = "11px sans-serif"; ctx.fillText(String(it.label), x + 7, y - 5); }
        } else if (it.kind === "truth") {
          ctx.strokeStyle = "#111"; ctx.lineWidth = 1.2;
          ctx.arc(x, y, Math.max(4, 8 * near), 0, 2 * Math.PI); ctx.stroke();
        } else {
          ctx.fillStyle = "#9467bd";
          ctx.rect(x - 2.5, y - 2.5, 5, 5); ctx.fill();
        }
      });
      // axes gizmo: world X (red), Y (green), Z (blue)
      var gx = 40, gy = h - 40;
      [["X", "#d62728", [1, 0, 0]], ["Y", "#2ca02c", [0, 1, 0]], ["Z", "#1f77b4", [0, 0, 1]]].forEach(function (a) {
        var q = apply(view, a[2]);
        ctx.strokeStyle = a[1]; ctx.fillStyle = a[1]; ctx.lineWidth = 2; ctx.beginPath();
        ctx.moveTo(gx, gy); ctx.lineTo(gx + 24 * q[0], gy + 24 * q[1]); ctx.stroke();
        ctx.font = "11px sans-serif"; ctx.fillText(a[0], gx + 28 * q[0] - 3, gy + 28 * q[1] + 4);
      });
    }

    var dragging = false, lastX = 0, lastY = 0;
    canvas.addEventListener("pointerdown", function (e) {
      dragging = true; lastX = e.clientX; lastY = e.clientY;
      if (canvas.setPointerCapture) { canvas.setPointerCapture(e.pointerId); }
    });
    canvas.addEventListener("pointermove", function (e) {
      if (!dragging) {
        if (allLabels) { return; }
        var box = canvas.getBoundingClientRect(), px = e.clientX - box.left, py = e.clientY - box.top;
        var best = -1, bestD = 64;  // within 8 px
        drawn.forEach(function (d) {
          var dd = (d[0] - px) * (d[0] - px) + (d[1] - py) * (d[1] - py);
          if (dd < bestD) { bestD = dd; best = d[2]; }
        });
        if (best !== hover) { hover = best; draw(); }
        return;
      }
      var dx = e.clientX - lastX, dy = e.clientY - lastY;
      lastX = e.clientX; lastY = e.clientY;
      view = mul(mul(rotY(-dx * 0.01), rotX(dy * 0.01)), view);
      draw();
    });
    function release() { dragging = false; }
    canvas.addEventListener("pointerup", release);
    canvas.addEventListener("pointercancel", release);
    canvas.addEventListener("wheel", function (e) {
      e.preventDefault();
      zoom = Math.min(8, Math.max(0.2, zoom * Math.exp(-e.deltaY * 0.001)));
      draw();
    }, { passive: false });
    document.getElementById("view3d-reset").addEventListener("click", function () {
      view = start; zoom = 1; draw();
    });
    if (showTruth) { showTruth.addEventListener("change", draw); }
    if (colourBy) { colourBy.addEventListener("change", draw); }
    if (showUnreliable) { showUnreliable.addEventListener("change", draw); }
    if (cameraSlider && data.cameras && data.cameras.length) {
      cameraSlider.max = String(data.cameras.length - 1);
      cameraSlider.addEventListener("input", function () {
        var f = parseInt(cameraSlider.value, 10);
        view = data.cameras[f];
        cameraLabel.textContent = "seen by the camera of frame " + data.camera_frames[f];
        draw();
      });
    }
    window.addEventListener("resize", draw);
    draw();
  }

  // --- long tables: the first rows, and a button for all of them --------------
  function setupFolding() {
    Array.prototype.forEach.call(document.querySelectorAll("table[data-fold]"), function (table) {
      var limit = parseInt(table.getAttribute("data-fold"), 10);
      var button = table.nextElementSibling && table.nextElementSibling.querySelector(".fold-toggle");
      var open = false;
      function apply() {
        Array.prototype.forEach.call(table.tBodies[0].rows, function (row, k) { row.hidden = !open && k >= limit; });
        if (button) {
          button.textContent = open ? "show the first " + limit + " rows" : "show all " + table.tBodies[0].rows.length + " rows";
        }
      }
      table.foldRows = apply;
      if (button) { button.addEventListener("click", function () { open = !open; apply(); }); }
      apply();
    });
  }

  // --- sortable tables ----------------------------------------------------
  function setupSorting() {
    Array.prototype.forEach.call(document.querySelectorAll("table.sortable"), function (table) {
      var headers = table.querySelectorAll("thead th");
      Array.prototype.forEach.call(headers, function (th, col) {
        var ascending = true;
        th.title = "sort";
        th.addEventListener("click", function () {
          var body = table.tBodies[0];
          var rows = Array.prototype.slice.call(body.rows);
          rows.sort(function (a, b) {
            var x = a.cells[col].getAttribute("data-sort") || a.cells[col].textContent;
            var y = b.cells[col].getAttribute("data-sort") || b.cells[col].textContent;
            var nx = parseFloat(x), ny = parseFloat(y);
            var order = (!isNaN(nx) && !isNaN(ny)) ? nx - ny : x.localeCompare(y);
            return ascending ? order : -order;
          });
          ascending = !ascending;
          rows.forEach(function (r) { body.appendChild(r); });
          if (table.foldRows) { table.foldRows(); }
        });
      });
    });
  }

  setupPlayer();
  setupView3d();
  setupFolding();
  setupSorting();
  status.setAttribute("data-ready", "yes");
})();
"""

# Runs first, in <head>: records any uncaught error so a headless test can see it.
ERROR_TRAP_JS = r"""
window.addEventListener("error", function (e) {
  var s = document.getElementById("js-status");
  var text = (e.message || "error") + " @" + (e.lineno || "?");
  if (s) { s.setAttribute("data-errors", (s.getAttribute("data-errors") || "") + text + "; "); }
});
"""
