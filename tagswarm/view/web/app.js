// tagswarm live view: draws the arena from the view server's WebSocket messages.
//
// Messages (JSON): "scene" (static arena, arena frame), "state" (robots etc., map frame),
// "camera" (a JPEG thumbnail and the detections reprojected on it).  The page sends
// {"type": "select", "robot": K} to choose the camera.  It reconnects on its own
// (the view restarted) and starts over when the run changes.
//
// SVG layout: the root is in "screen" units (metres, y down); #world flips y so that
// everything inside is in the ARENA frame (x right, y up, metres); #map inside it is
// placed by T_arena_map so that everything inside is in the MAP frame, like the
// server's poses.  Each robot's fused pose is a <g class="fused robot-fused"> with
// data-robot, data-x, data-y, data-yaw (map frame, metres/radians), data-stamp (ns)
// and data-source ("map" or "correction") so that tests can read what is drawn.
"use strict";

(() => {
  const SVGNS = "http://www.w3.org/2000/svg";
  const COLORS = ["#4cc9f0", "#f72585", "#ffd166", "#06d6a0", "#b388ff", "#ff8c42", "#90be6d", "#f94144",
                  "#43aa8b", "#f9c74f", "#577590", "#ff99c8"];
  const TRAIL_MAX = 900;          // points per trail
  const TRAIL_STEP_M = 0.01;      // a new trail point once the robot moved this far
  const STALE_S = 2.5;            // no state for this long: the system is not running

  const $ = (id) => document.getElementById(id);
  const body = document.body;
  const arena = $("arena");

  /** Create an SVG element with attributes, appended to parent when given. */
  function el(tag, attrs, parent) {
    const e = document.createElementNS(SVGNS, tag);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    if (parent) parent.appendChild(e);
    return e;
  }
  const deg = (rad) => rad * 180 / Math.PI;
  const color = (id) => COLORS[((id % COLORS.length) + COLORS.length) % COLORS.length];
  const fmt = (x, digits) => (x === null || x === undefined ? "–" : Number(x).toFixed(digits));

  // ------------------------------------------------------------------ state of the page
  const view = window.__view = {
    connected: false, connects: 0, states: 0, cameras: 0, scene: null, state: null,
    epoch: null, runId: null, selected: null, lastStateAt: 0, rateTimes: [],
  };
  let ws = null;
  let retry = 0;
  let layers = null;          // SVG groups, rebuilt with each scene
  let geom = null;            // sizes derived from the scene
  const robots = new Map();   // id -> drawn elements and trails

  // ------------------------------------------------------------------ connection
  function connect() {
    const proto = location.protocol === "https:" ? "wss" : "ws";
    ws = new WebSocket(`${proto}://${location.host}/ws`);
    ws.onopen = () => {
      retry = 0;
      view.connected = true;
      view.connects += 1;
      body.dataset.connects = String(view.connects);
      showConnection();
      if (view.selected !== null) sendSelect();
    };
    ws.onmessage = (ev) => {
      let msg;
      try { msg = JSON.parse(ev.data); } catch (e) { return; }  // never let one bad frame stop the page
      try { handle(msg); } catch (e) { console.error("tagswarm view:", e); }
    };
    ws.onclose = () => {
      view.connected = false;
      showConnection();
      const delay = Math.min(2000, 250 * 2 ** retry);
      retry += 1;
      setTimeout(connect, delay);
    };
    ws.onerror = () => { /* onclose follows and retries */ };
  }

  function sendSelect() {
    if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ type: "select", robot: view.selected }));
  }

  function showConnection() {
    const c = $("conn");
    const stale = view.connected && (performance.now() - view.lastStateAt) / 1000 > STALE_S;
    c.className = "conn " + (view.connected ? (stale ? "stale" : "up") : "down");
    c.querySelector("span").textContent = !view.connected ? "reconnecting…"
      : stale ? "connected · no data" : `live · ${updateRate().toFixed(0)} updates/s`;
    body.dataset.connected = view.connected ? "1" : "0";
  }

  /** States received per second over the last 3 s (or since the first one, if later). */
  function updateRate() {
    const now = performance.now();
    view.rateTimes = view.rateTimes.filter((t) => now - t < 3000);
    const n = view.rateTimes.length;
    if (n < 2) return 0;
    return (n - 1) / Math.max((now - view.rateTimes[0]) / 1000, 0.001);
  }

  function handle(msg) {
    if (msg.type === "scene") onScene(msg);
    else if (msg.type === "state") onState(msg);
    else if (msg.type === "camera") onCamera(msg);
  }

  // ------------------------------------------------------------------ scene (static)
  function onScene(scene) {
    view.scene = scene;
    $("scenario").textContent = scene.scenario;
    const a = scene.arena;
    const sx = a.size_x_m, sy = a.size_y_m;
    const margin = Math.max(sx, sy) * 0.06 + a.wall_thickness_m;
    const big = Math.max(sx, sy);
    geom = {
      lw: big / 450, fs: big / 42, L: scene.robot.length_m, W: scene.robot.width_m,
      radius: scene.robot.radius_m, map: scene.map_in_arena,
    };
    arena.setAttribute("viewBox", `${-sx / 2 - margin} ${-sy / 2 - margin} ${sx + 2 * margin} ${sy + 2 * margin}`);
    arena.replaceChildren();
    robots.clear();
    const world = el("g", { id: "world", transform: "scale(1,-1)" }, arena);
    el("rect", { class: "floor", x: -sx / 2, y: -sy / 2, width: sx, height: sy }, world);
    const grid = el("g", { class: "grid" }, world);
    const labels0 = el("g", { class: "ticks" }, arena);
    for (let x = Math.ceil(-sx / 2); x <= sx / 2; x += 1) {
      el("line", { x1: x, y1: -sy / 2, x2: x, y2: sy / 2, "stroke-width": geom.lw * (x === 0 ? 1.4 : 0.8),
                   class: x === 0 ? "axis" : "" }, grid);
      el("text", { x, y: sy / 2 + margin * 0.55, "font-size": geom.fs * 0.7, "text-anchor": "middle",
                   class: "tick-label" }, labels0).textContent = `${x} m`;
    }
    for (let y = Math.ceil(-sy / 2); y <= sy / 2; y += 1) {
      el("line", { x1: -sx / 2, y1: y, x2: sx / 2, y2: y, "stroke-width": geom.lw * (y === 0 ? 1.4 : 0.8),
                   class: y === 0 ? "axis" : "" }, grid);
      el("text", { x: -sx / 2 - margin * 0.5, y: -y + geom.fs * 0.25, "font-size": geom.fs * 0.7,
                   "text-anchor": "middle", class: "tick-label" }, labels0).textContent = `${y}`;
    }
    for (const [cx, cy, hx, hy] of a.walls) {
      el("rect", { class: "wall", x: cx - hx, y: cy - hy, width: 2 * hx, height: 2 * hy }, world);
    }
    for (const [x, y, yaw, lx, ly] of a.obstacles) {
      el("rect", { class: "obstacle", x: -lx / 2, y: -ly / 2, width: lx, height: ly, "stroke-width": geom.lw,
                   transform: `translate(${x} ${y}) rotate(${deg(yaw)})` }, world);
    }
    for (const [id, x, y, yaw, size] of scene.landmarks) {
      const g = el("g", { class: "landmark-g", transform: `translate(${x} ${y}) rotate(${deg(yaw)})` }, world);
      el("rect", { class: "landmark", x: -0.02, y: -size / 2, width: 0.04, height: size, "stroke-width": geom.lw },
         g);
      el("text", { x: x, y: -y - size, "font-size": geom.fs * 0.7, "text-anchor": "middle", class: "tick-label" },
         labels0).textContent = `tag ${id}`;
    }
    const [mx, my, myaw] = geom.map;
    const map = el("g", { id: "map", transform: `translate(${mx} ${my}) rotate(${deg(myaw)})` }, world);
    layers = {
      world, map,
      trails: el("g", { id: "trails" }, map),
      sees: el("g", { id: "sees", class: "sees" }, map),
      ellipses: el("g", { id: "ellipses" }, map),
      odom: el("g", { id: "odom" }, map),
      truth: el("g", { id: "truth" }, map),
      fused: el("g", { id: "fused" }, map),
      events: el("g", { id: "events-layer" }, map),
      labels: el("g", { id: "labels" }, arena),
    };
    const sel = $("robot-select");
    if (view.selected === null && scene.robot_ids.length) {
      view.selected = scene.robot_ids.includes(scene.origin_id) ? scene.origin_id : scene.robot_ids[0];
      sendSelect();
    }
    fillSelect(sel, scene.robot_ids);
    if (view.state) onState(view.state, true);
  }

  /** Map-frame point -> root (screen, y down) coordinates. */
  function mapToScreen(x, y) {
    const [mx, my, myaw] = geom.map;
    const c = Math.cos(myaw), s = Math.sin(myaw);
    return [mx + c * x - s * y, -(my + s * x + c * y)];
  }

  /** Arena-frame point -> map frame. */
  function arenaToMap(x, y) {
    const [mx, my, myaw] = geom.map;
    const c = Math.cos(myaw), s = Math.sin(myaw);
    const dx = x - mx, dy = y - my;
    return [c * dx + s * dy, -s * dx + c * dy];
  }

  // ------------------------------------------------------------------ robots
  function robotEls(id) {
    let r = robots.get(id);
    if (r) return r;
    const c = color(id), { lw, L, W, fs } = geom;
    r = { id, color: c, trail: [], truthTrail: [] };
    r.truthTrailEl = el("polyline", { class: "truth-trail", "stroke-width": lw }, layers.trails);
    r.trailEl = el("polyline", { class: "trail", stroke: c, "stroke-width": lw * 1.4, opacity: 0.7 }, layers.trails);
    r.ellipse = el("ellipse", { class: "ellipse", fill: c, "fill-opacity": 0.16, stroke: c, "stroke-width": lw,
                                "data-robot": id }, layers.ellipses);
    r.odom = el("g", { class: "odom", "data-robot": id }, layers.odom);
    el("rect", { x: -L / 2, y: -W / 2, width: L, height: W, stroke: c, "stroke-width": lw * 1.2,
                 "stroke-dasharray": `${lw * 4} ${lw * 3}` }, r.odom);
    r.truth = el("g", { class: "truth", "data-robot": id }, layers.truth);
    el("rect", { x: -L / 2 - lw * 2, y: -W / 2 - lw * 2, width: L + lw * 4, height: W + lw * 4,
                 "stroke-width": lw * 1.5 }, r.truth);
    el("line", { x1: 0, y1: 0, x2: L / 2 + 0.12, y2: 0, "stroke-width": lw * 1.5 }, r.truth);
    r.fused = el("g", { class: "fused robot-fused", "data-robot": id }, layers.fused);
    el("rect", { class: "body", x: -L / 2, y: -W / 2, width: L, height: W, rx: W * 0.12, fill: c,
                 "stroke-width": lw * 0.8 }, r.fused);
    el("path", { class: "nose", d: `M ${L * 0.45} 0 L ${L * 0.1} ${W * 0.3} L ${L * 0.1} ${-W * 0.3} Z` }, r.fused);
    r.label = el("text", { class: "label", "font-size": fs, "stroke-width": fs * 0.22, "text-anchor": "middle" },
                 layers.labels);
    r.labelMain = el("tspan", {}, r.label);
    r.labelSub = el("tspan", { class: "sub", "font-size": fs * 0.75, dx: fs * 0.3 }, r.label);
    robots.set(id, r);
    return r;
  }

  function place(g, p) {
    if (!p) { g.setAttribute("display", "none"); return; }
    g.removeAttribute("display");
    g.setAttribute("transform", `translate(${p[0]} ${p[1]}) rotate(${deg(p[2])})`);
  }

  function pushTrail(list, p) {
    const last = list[list.length - 1];
    if (!last || Math.hypot(p[0] - last[0], p[1] - last[1]) >= TRAIL_STEP_M) {
      list.push([p[0], p[1]]);
      if (list.length > TRAIL_MAX) list.splice(0, list.length - TRAIL_MAX);
      return true;
    }
    return false;
  }

  function clearRun() {
    for (const r of robots.values()) {
      for (const e of [r.truthTrailEl, r.trailEl, r.ellipse, r.odom, r.truth, r.fused, r.label]) e.remove();
    }
    robots.clear();
    if (layers) { layers.sees.replaceChildren(); layers.events.replaceChildren(); }
  }

  // ------------------------------------------------------------------ state (moving)
  function onState(st, redraw) {
    view.state = st;
    if (!redraw) {
      view.states += 1;
      view.lastStateAt = performance.now();
      view.rateTimes.push(view.lastStateAt);
      body.dataset.states = String(view.states);
    }
    if (!layers) return;  // the scene comes first on every connection
    if (st.epoch !== view.epoch || (st.run_id && view.runId && st.run_id !== view.runId)) clearRun();
    view.epoch = st.epoch;
    if (st.run_id) view.runId = st.run_id;
    body.dataset.epoch = String(st.epoch);
    body.dataset.runId = st.run_id || "";
    body.dataset.simNs = String(st.sim_ns);
    $("run-id").textContent = st.run_id || st.run || "–";
    $("run-id").title = st.run_id || "";
    $("sim-time").textContent = `${(st.sim_ns / 1e9).toFixed(1)} s`;
    $("rtf").textContent = st.rtf === null || st.rtf === undefined ? "–" : `${st.rtf.toFixed(2)}×`;
    $("clock").textContent = st.clock || "–";
    $("waiting").classList.toggle("hidden", st.robots.length > 0);

    const where = new Map();  // id -> map-frame position used for "sees" lines and labels
    const seen = new Set();
    for (const rb of st.robots) {
      const r = robotEls(rb.id);
      seen.add(rb.id);
      const dead = rb.alive === false;
      place(r.truth, rb.truth);
      place(r.odom, rb.odom);
      const f = rb.fused;
      if (f) {
        place(r.fused, [f.x, f.y, f.yaw]);
        const d = r.fused.dataset;
        d.x = String(f.x); d.y = String(f.y); d.yaw = String(f.yaw);
        d.stamp = String(f.stamp_ns); d.source = f.source;
        const [ea, eb, eang] = f.ellipse;
        r.ellipse.removeAttribute("display");
        r.ellipse.setAttribute("cx", f.x); r.ellipse.setAttribute("cy", f.y);
        r.ellipse.setAttribute("rx", Math.max(ea, 0.005)); r.ellipse.setAttribute("ry", Math.max(eb, 0.005));
        r.ellipse.setAttribute("transform", `rotate(${deg(eang)} ${f.x} ${f.y})`);
        if (pushTrail(r.trail, [f.x, f.y])) r.trailEl.setAttribute("points", r.trail.map((q) => q.join(",")).join(" "));
      } else {
        place(r.fused, null);
        r.ellipse.setAttribute("display", "none");
      }
      if (rb.truth && pushTrail(r.truthTrail, rb.truth)) {
        r.truthTrailEl.setAttribute("points", r.truthTrail.map((q) => q.join(",")).join(" "));
      }
      for (const e of [r.fused, r.ellipse, r.odom]) e.classList.toggle("dead", dead);
      const anchor = f ? [f.x, f.y] : rb.truth;
      if (anchor) {
        where.set(rb.id, anchor);
        const [lx, ly] = mapToScreen(anchor[0], anchor[1]);
        r.label.removeAttribute("display");
        r.label.setAttribute("x", lx);
        r.label.setAttribute("y", ly - geom.radius - geom.fs * 0.35);
        r.labelMain.textContent = String(rb.id);
        r.labelSub.textContent = rb.mode ? `${rb.mode}${dead ? " · gone" : ""}` : (dead ? "gone" : "");
        r.labelSub.setAttribute("class", `sub ${rb.mode || ""}`);
      } else {
        r.label.setAttribute("display", "none");
      }
    }
    for (const [id, r] of robots) {
      if (!seen.has(id)) {
        for (const e of [r.truthTrailEl, r.trailEl, r.ellipse, r.odom, r.truth, r.fused, r.label]) e.remove();
        robots.delete(id);
      }
    }
    drawSees(st, where);
    drawEvents(st);
    fillEvents(st);
    fillTable(st);
    fillSystem(st);
    fillSelect($("robot-select"), st.robots.map((rb) => rb.id));
    showConnection();
  }

  function drawSees(st, where) {
    const g = layers.sees;
    g.replaceChildren();
    const landmarks = new Map((view.scene.landmarks || []).map(([id, x, y]) => [id, arenaToMap(x, y)]));
    for (const s of st.sees) {
      const a = where.get(s.from);
      const b = s.kind === "robot" ? where.get(s.to) : landmarks.get(s.to);
      if (!a || !b) continue;
      const fade = Math.max(0.15, 1 - s.age_s);
      el("line", { x1: a[0], y1: a[1], x2: b[0], y2: b[1], "stroke-width": geom.lw * 2.2,
                   opacity: 0.85 * fade, "data-from": s.from, "data-to": s.to, "data-kind": s.kind }, g);
      // an arrow head near the target: who sees whom is directed
      const dx = b[0] - a[0], dy = b[1] - a[1], n = Math.hypot(dx, dy) || 1;
      const ux = dx / n, uy = dy / n, tip = [b[0] - ux * geom.radius, b[1] - uy * geom.radius];
      const h = geom.fs * 0.55;
      el("path", { d: `M ${tip[0]} ${tip[1]} L ${tip[0] - ux * h - uy * h * 0.5} ${tip[1] - uy * h + ux * h * 0.5} ` +
                      `L ${tip[0] - ux * h + uy * h * 0.5} ${tip[1] - uy * h - ux * h * 0.5} Z`,
                   fill: "#7dffb0", opacity: 0.85 * fade }, g);
    }
  }

  /** A fading marker where each recent event happened: re-localised (ring at the new
   *  estimate, line from the old one) or kidnapped (a cross); map frame. */
  function drawEvents(st) {
    const g = layers.events;
    g.replaceChildren();
    const ttl = view.scene.marker_ttl_s || 3;
    for (const e of st.events || []) {
      if (!e.at || e.age_s === null || e.age_s > ttl) continue;
      const fade = Math.max(0, 1 - e.age_s / ttl);
      const [x, y] = e.at, r = geom.radius * (1.3 + 0.6 * (1 - fade));
      const attrs = { class: `${e.kind === "kidnap" ? "kidnap" : "reloc"}-marker`, opacity: 0.3 + 0.7 * fade,
                      "data-robot": e.robot, "data-kind": e.kind, "data-stamp": e.stamp_ns };
      const m = el("g", attrs, g);
      if (e.kind === "kidnap") {
        const h = r * 0.7;
        el("path", { d: `M ${x - h} ${y - h} L ${x + h} ${y + h} M ${x - h} ${y + h} L ${x + h} ${y - h}`,
                     "stroke-width": geom.lw * 3 }, m);
      } else {
        el("circle", { cx: x, cy: y, r, "stroke-width": geom.lw * 3 }, m);
        if (e.from) {
          el("line", { x1: e.from[0], y1: e.from[1], x2: x, y2: y, "stroke-width": geom.lw * 1.5,
                       "stroke-dasharray": `${geom.lw * 4} ${geom.lw * 3}` }, m);
        }
      }
    }
  }

  function fillEvents(st) {
    const c = st.event_counts || { relocalisations: 0, kidnaps: 0 };
    $("event-counts").textContent = `${c.relocalisations} re-localised · ${c.kidnaps} kidnapped`;
    const items = (st.events || []).slice(0, 8).map((e) => {
      const t = `${(e.stamp_ns / 1e9).toFixed(1)} s`;
      const what = e.kind === "kidnap" ? `robot ${e.robot} kidnapped (${e.action})`
        : `robot ${e.robot} re-localised: ${fmt(e.jump_m, 2)} m on ${e.evidence} obs.`;
      return `<li class="${e.kind}" data-kind="${e.kind}" data-robot="${e.robot}">${t} <b>${what}</b></li>`;
    });
    $("events").innerHTML = items.length ? items.join("") : '<li class="none">none yet</li>';
  }

  function fillTable(st) {
    const tb = document.querySelector("#robots tbody");
    const rows = st.robots.map((rb) => {
      const origin = rb.id === st.origin_id ? '<span class="badge">origin</span>' : "";
      const err = rb.error_m === null ? "–" : `${(rb.error_m * 100).toFixed(1)} cm`;
      const a95 = rb.fused ? `${(rb.fused.ellipse[0] * 100).toFixed(1)} cm` : "–";
      const fix = rb.fix_age_s === null ? "–" : `${rb.fix_age_s.toFixed(1)} s`;
      const loc = rb.time_localised === null || rb.time_localised === undefined ? "–"
        : `${(rb.time_localised * 100).toFixed(0)}%`;
      const mode = rb.mode ? `<span class="mode ${rb.mode}">${rb.mode}</span>` : "–";
      const cls = [rb.id === view.selected ? "selected" : "", rb.alive === false ? "dead" : ""].join(" ");
      return `<tr data-robot="${rb.id}" class="${cls}"><td><span class="swatch" style="background:${color(rb.id)}">` +
        `</span></td><td>robot ${rb.id}${origin}</td><td>${mode}</td><td class="num">${err}</td>` +
        `<td class="num">${a95}</td><td class="num">${fix}</td><td class="num">${rb.fixes ?? "–"}</td>` +
        `<td class="num">${loc}</td></tr>`;
    });
    tb.innerHTML = rows.join("");
  }

  function fillSystem(st) {
    const lines = [];
    const add = (k, v, bad) => lines.push(`<div class="${bad ? "bad" : ""}">${k}<b>${v}</b></div>`);
    add("Zenoh run", st.run);
    add("map stamp", st.map_stamp_ns === null ? "–" : `${(st.map_stamp_ns / 1e9).toFixed(2)} s`);
    const server = st.processes.server;
    if (server) {
      add("localised robots", server.counters.localised ?? "–");
      add("observations fused", server.counters.observations ?? "–");
    }
    const world = st.processes.world;
    if (world && world.counters.frames_rendered !== undefined) add("frames rendered", world.counters.frames_rendered);
    const rej = Object.entries(st.rejected || {});
    const total = rej.reduce((n, [, v]) => n + v, 0);
    add("bad messages dropped", total ? rej.map(([k, v]) => `${k} ${v}`).join(", ") : "0", total > 0);
    add("page updates", `${updateRate().toFixed(1)} /s`);
    $("net").innerHTML = lines.join("");
  }

  function fillSelect(sel, ids) {
    const want = ids.map(String).join(",");
    if (sel.dataset.ids === want) return;
    sel.dataset.ids = want;
    sel.replaceChildren(...ids.map((id) => {
      const o = document.createElement("option");
      o.value = String(id);
      o.textContent = `robot ${id}`;
      return o;
    }));
    if (view.selected !== null) sel.value = String(view.selected);
  }

  function select(id) {
    if (id === view.selected) return;
    view.selected = id;
    $("robot-select").value = String(id);
    $("cam-img").removeAttribute("src");
    $("cam-overlay").replaceChildren();
    $("cam-empty").classList.remove("hidden");
    $("cam-caption").innerHTML = "&nbsp;";
    sendSelect();
    if (view.state) fillTable(view.state);
  }

  // ------------------------------------------------------------------ camera
  function onCamera(msg) {
    if (msg.robot !== view.selected) return;
    view.cameras += 1;
    body.dataset.cameras = String(view.cameras);
    $("cam").style.aspectRatio = `${msg.width} / ${msg.height}`;
    $("cam-img").src = `data:image/jpeg;base64,${msg.jpeg}`;
    $("cam-empty").classList.add("hidden");
    const ov = $("cam-overlay");
    ov.setAttribute("viewBox", `-0.5 -0.5 ${msg.width} ${msg.height}`);
    ov.replaceChildren();
    const fs = msg.width / 30;
    for (const d of msg.detections) {
      const c = d.kind === "robot" ? color(d.target) : "#ffffff";
      for (const p of d.polys) {
        el("polygon", { points: p.uv.map((q) => q.join(",")).join(" "), stroke: c, "data-tag": p.tag }, ov);
      }
      const text = `${d.kind === "robot" ? "robot" : "tag"} ${d.target} · ${d.range_m.toFixed(1)} m`;
      const half = text.length * fs * 0.3;  // about half the label's width: keep it inside the frame
      const x = Math.min(Math.max(d.label[0], half), msg.width - half);
      const y = Math.max(d.label[1] - fs * 0.4, fs);
      el("text", { x, y, fill: c, "font-size": fs, "text-anchor": "middle" }, ov).textContent = text;
    }
    const n = msg.detections.length;
    $("cam-caption").textContent = `robot ${msg.robot} · ${msg.camera} · t = ${(msg.stamp_ns / 1e9).toFixed(2)} s · ` +
      `${msg.source_size[0]}×${msg.source_size[1]} · ${n} detection${n === 1 ? "" : "s"} (agent's estimate reprojected)`;
  }

  // ------------------------------------------------------------------ wiring
  $("robot-select").addEventListener("change", (ev) => select(Number(ev.target.value)));
  document.querySelector("#robots tbody").addEventListener("click", (ev) => {
    const tr = ev.target.closest("tr[data-robot]");
    if (tr) select(Number(tr.dataset.robot));
  });
  setInterval(showConnection, 500);
  connect();
})();
