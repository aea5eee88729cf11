/* btmission viewer: a run's records folded at a chosen time T into a meshcat 3D scene, each
 * agent's behaviour tree (Groot2's colours), its blackboard, a task table, a timeline and an
 * event list. The same code watches a live run (records stream in over Server-Sent Events and T
 * follows the newest) and replays a log (play, pause, speed, a time slider), served by
 * `btmission view LOG` or embedded in one offline HTML file (`--html`).
 *
 * Records are the event log's JSON lines ({t, ev, ...}); see btmission/viz/feed.py. */
(function () {
  "use strict";
  const CFG = window.BTM_CONFIG || {};
  const THREE = MeshCat.THREE;
  const TASK_COLORS = {
    open: "#3b82f6", assigned: "#f59e0b", committed: "#a855f7", done: "#22c55e",
    unreachable: "#ef4444", failed: "#b91c1c", cancelled: "#9ca3af",
  };
  const AGENT_COLORS = ["#38bdf8", "#f472b6", "#a3e635", "#fb923c", "#c084fc", "#facc15",
    "#2dd4bf", "#f87171", "#818cf8", "#4ade80", "#e879f9", "#fbbf24"];
  const GLYPH = { fallback: "?", sequence: "→", condition: "◇", action: "▶" };
  const TRAIL_S = 60;          // trail length (s of mission time)
  const PANEL_MS = 200;        // DOM panels refresh at most this often
  const MAX_POSES = 40000;     // per agent (over an hour at 10 Hz); past it the older are thinned
  const $ = (id) => document.getElementById(id);

  // ------------------------------------------------------------------------ the model
  function bisect(ts, t) {     // last index i with ts[i] <= t, or -1
    let lo = 0, hi = ts.length - 1, ans = -1;
    while (lo <= hi) {
      const mid = (lo + hi) >> 1;
      if (ts[mid] <= t) { ans = mid; lo = mid + 1; } else { hi = mid - 1; }
    }
    return ans;
  }
  function lastAt(list, t) {   // list of [t, ...] sorted by t: the last entry at or before t
    const i = bisect(list.tsCache || (list.tsCache = []), t);
    return i >= 0 ? list[i] : null;
  }
  function pushTimed(list, entry) {
    list.push(entry);
    (list.tsCache || (list.tsCache = [])).push(entry[0]);
  }

  class Agent {
    constructor(id, index, start) {
      this.id = id;
      this.color = AGENT_COLORS[index % AGENT_COLORS.length];
      this.start = start || [0, 0, 0];
      this.pt = []; this.px = []; this.py = []; this.pz = []; this.pyaw = []; this.pmode = [];
      this.routes = []; this.tasks = []; this.stages = []; this.trees = []; this.lost = [];
      this.nodes = null;
      this.cache = null;       // tree status folded up to cache.t
    }
    addPose(r) {
      const n = this.pt.length;
      if (n && r.t < this.pt[n - 1]) return;          // (a live latest pose already kept)
      if (n && r.t === this.pt[n - 1]) { this.pt.pop(); this.px.pop(); this.py.pop(); this.pz.pop(); this.pyaw.pop(); this.pmode.pop(); }
      this.pt.push(r.t); this.px.push(r.p[0]); this.py.push(r.p[1]); this.pz.push(r.p[2]);
      this.pyaw.push(r.yaw || 0); this.pmode.push(r.mode || "");
      if (this.pt.length > MAX_POSES) this.thin();
    }
    thin() {                    // a long live run: every other pose of the older half goes
      const half = this.pt.length >> 1;
      for (const a of [this.pt, this.px, this.py, this.pz, this.pyaw, this.pmode]) {
        const kept = a.slice(0, half).filter((_, i) => i % 2 === 0);
        a.splice(0, half, ...kept);
      }
    }
    poseAt(t) {
      const i = bisect(this.pt, t);
      if (i < 0) return this.pt.length ? null : { x: this.start[0], y: this.start[1], z: this.start[2], yaw: 0, mode: "" };
      const j = i + 1;
      if (j < this.pt.length && this.pt[j] - this.pt[i] < 5) {
        const a = (t - this.pt[i]) / (this.pt[j] - this.pt[i]);
        let dy = this.pyaw[j] - this.pyaw[i];
        dy = Math.atan2(Math.sin(dy), Math.cos(dy));
        return { x: this.px[i] + a * (this.px[j] - this.px[i]), y: this.py[i] + a * (this.py[j] - this.py[i]),
          z: this.pz[i] + a * (this.pz[j] - this.pz[i]), yaw: this.pyaw[i] + a * dy, mode: this.pmode[i] };
      }
      return { x: this.px[i], y: this.py[i], z: this.pz[i], yaw: this.pyaw[i], mode: this.pmode[i] };
    }
    trail(t0, t1) {
      const a = Math.max(0, bisect(this.pt, t0)), b = bisect(this.pt, t1);
      const out = [];
      for (let i = a; i <= b; i++) out.push(this.px[i], this.py[i], this.pz[i]);
      return out;
    }
    treeAt(t) {                 // {status: [..], bb: Map} folded from the tree records up to t
      if (!this.nodes) return null;
      let c = this.cache;
      if (!c || t < c.t) {
        c = this.cache = { t: -Infinity, i: 0, status: this.nodes.map(() => "INVALID"), bb: new Map(), changedAt: new Map() };
      }
      while (c.i < this.trees.length && this.trees[c.i][0] <= t) {
        const [tt, changes, bb, unset] = this.trees[c.i];
        for (const [uid, , now] of changes) if (uid < c.status.length) c.status[uid] = now;
        if (bb) for (const k of Object.keys(bb)) { c.bb.set(k, bb[k]); c.changedAt.set(k, tt); }
        if (unset) for (const k of unset) { c.bb.delete(k); c.changedAt.delete(k); }
        c.i++;
      }
      c.t = t;
      return c;
    }
  }

  class Model {
    constructor() {
      this.agents = new Map(); this.tasks = new Map(); this.events = [];
      this.header = null; this.end = null; this.tEnd = 0; this.count = 0; this.version = 0;
    }
    agent(id, start) {
      let a = this.agents.get(id);
      if (!a) { a = new Agent(id, this.agents.size, start); this.agents.set(id, a); }
      return a;
    }
    add(records) {
      for (const r of records) this.add1(r);
      this.count += records.length;
      if (records.length) this.version++;
    }
    add1(r) {
      const t = r.t;
      if (t > this.tEnd && r.ev !== "header") this.tEnd = t;
      switch (r.ev) {
        case "header":
          this.header = r;
          for (const a of r.agents || []) this.agent(a.id, a.start);
          break;
        case "pose": this.agent(r.agent).addPose(r); break;
        case "task_added": {
          const task = { id: r.task, type: r.type, fields: r.fields || {}, priority: r.priority, added: t, states: [] };
          pushTimed(task.states, [t, "open", null, ""]);
          this.tasks.set(r.task, task);
          this.note(r, `task ${r.task} added (${r.type})${r.by && r.by !== "mission" ? " by " + r.by : ""}`);
          break;
        }
        case "task": {
          const task = this.tasks.get(r.task);
          if (task) pushTimed(task.states, [t, r.state, r.agent, r.reason || ""]);
          this.note(r, `${r.task} ${r.state}${r.agent ? " → " + r.agent : ""}${r.reason ? " (" + r.reason + ")" : ""}`,
            r.state === "unreachable" || r.state === "failed");
          break;
        }
        case "agent_task": pushTimed(this.agent(r.agent).tasks, [t, r.task]); break;
        case "stage": pushTimed(this.agent(r.agent).stages, [t, r.action, r.task]); break;
        case "route": pushTimed(this.agent(r.agent).routes, [t, r.points, r.task]); break;
        case "tree": {
          const a = this.agent(r.agent);
          if (r.nodes) { a.nodes = r.nodes; a.cache = null; }
          pushTimed(a.trees, [t, r.changes || [], r.blackboard || null, r.unset || null]);
          if (a.cache && t < a.cache.t) a.cache = null;
          break;
        }
        case "agent_lost":
          pushTimed(this.agent(r.agent).lost, [t, r.reason]);
          this.note(r, `${r.agent} lost: ${r.reason}`, true); break;
        case "collision": this.note(r, `${r.agent} collided with ${r.other}`, true); break;
        case "progress": this.note(r, `${r.agent} reports ${r.task} ${r.event}${r.reason ? " (" + r.reason + ")" : ""}`, r.event === "failed"); break;
        case "committed": this.note(r, `${r.agent} committed to ${r.task}`); break;
        case "link": this.note(r, `${r.agent} link ${r.up ? "restored" : "cut"}`, !r.up); break;
        case "vehicle_link": this.note(r, `${r.agent} vehicle ${r.up ? "heard again" : "lost"}${r.mode ? " (" + r.mode + ")" : ""}`, !r.up); break;
        case "command": this.note(r, `operator ${r.by}: ${r.command}${r.task ? " " + r.task : ""}${r.agent ? " " + r.agent : ""} ${r.ok ? "ok" : "refused: " + (r.error || "")}`, !r.ok); break;
        case "withdrawn": this.note(r, `${r.agent} withdrawn from ${r.task} (${r.reason})`); break;
        case "warning": this.note(r, `warning: ${r.message}`, true); break;
        case "leaf_error": this.note(r, `${r.agent || ""} ${r.leaf} raised ${r.error}: ${r.message}`, true); break;
        case "relocalized": this.note(r, `${r.agent} relocalised: ${r.localized ? "yes" : "no"} (${r.reason || ""})`); break;
        case "end": this.end = r; this.note(r, `end: ${r.reason}`); break;
        default: break;
      }
    }
    note(r, text, warn) { pushTimed(this.events, [r.t, text, !!warn]); }
    taskState(task, t) { return lastAt(task.states, t); }
    taskPoints(task) {          // the task's places: every [x, y, z] field, in field order
      const out = [];
      for (const [k, v] of Object.entries(task.fields)) {
        if (Array.isArray(v) && v.length === 3 && v.every((c) => typeof c === "number")) out.push([k, v]);
      }
      return out;
    }
  }

  // ------------------------------------------------------------------------ the 3D scene
  class Scene3D {
    constructor(pane, model) {
      this.model = model;
      this.pane = pane;
      this.viewer = new MeshCat.Viewer(pane);
      const v = this.viewer;
      // meshcat sizes its canvas to the window's height; this pane is not the whole window
      v.set_3d_pane_size = (w, h) => {
        w = w === undefined ? pane.offsetWidth : w;
        h = h === undefined ? pane.offsetHeight : h;
        v.camera.aspect = w / Math.max(h, 1);
        v.camera.updateProjectionMatrix();
        v.renderer.setSize(w, h);
        v.set_dirty();
      };
      new ResizeObserver(() => v.set_3d_pane_size()).observe(pane);
      const render = v.render.bind(v);
      v.render = () => { render(); this.afterRender(); };
      this.agents = new Map(); this.tasks = new Map(); this.labels = new Map();
      this.onPick = null;      // (kind, id): a click (not a drag) on an agent or a task
      this.onClick = null;     // (x, y) → true when it took the click (the console's add mode)
      let down = null;
      pane.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
      pane.addEventListener("pointerup", (e) => {
        if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 5) {
          if (!(this.onClick && this.onClick(e.clientX, e.clientY))) this.pick(e.clientX, e.clientY);
        }
        down = null;
      });
      this.marks = new Map();  // the console's picked points, by form field
      this.options = { trails: true, routes: true, labels: true };
      this.scale = 1;
      this.selected = null;
      this.lidar = null;
    }
    loadCommands(buf) {
      const u8 = new Uint8Array(buf);
      const dv = new DataView(u8.buffer, u8.byteOffset, u8.byteLength);
      let i = 0, n = 0;
      while (i + 4 <= u8.length) {
        const len = dv.getUint32(i);
        this.viewer.handle_command_bytearray(u8.subarray(i + 4, i + 4 + len));
        i += 4 + len; n++;
      }
      return n;
    }
    setBounds(bounds) {
      this.bounds = bounds;
      const [lo, hi] = bounds;
      const size = Math.max(hi[0] - lo[0], hi[1] - lo[1], 1);
      this.scale = Math.max(0.6, size / 150);
      // meshcat makes z up by rotating the scene and the camera's parent frame, so its orbit
      // controls only work around the origin; a mine is orbited around its centre: the scene
      // and the camera get plain frames, the camera z up, and new controls
      const v = this.viewer;
      v.scene.rotation.set(0, 0, 0);   // meshcat turns its whole scene z-up (Rx -90°): undone,
      v.scene.updateMatrixWorld(true); // so the scene, the camera and the labels share one frame
      v.set_transform(["Cameras", "default", "rotated"], new THREE.Matrix4().toArray());
      const sun = new THREE.DirectionalLight(0xffffff, 0.55);
      sun.position.set(0.35 * size, -0.6 * size, size);
      v.set_object(["Lights", "Sun"], sun);
      v.set_object(["Lights", "Sky"], new THREE.HemisphereLight(0xdde6f0, 0x3a3128, 0.45));
      const cam = v.camera;
      cam.up.set(0, 0, 1);
      cam.far = Math.max(1000, size * 10); cam.near = 0.05; cam.fov = 50;
      cam.updateProjectionMatrix();
      v.controls.dispose();
      v.set_camera(cam);
      // the map's bounds as a faint box: orientation on any map, even one without rock
      const box = new THREE.BoxGeometry(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
      const edges = new THREE.LineSegments(new THREE.EdgesGeometry(box), new THREE.LineBasicMaterial({ color: "#64748b", transparent: true, opacity: 0.5 }));
      edges.position.set((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2);
      v.set_object(["btm", "bounds"], edges);
      this.fit();
    }
    fit(top) {
      if (!this.bounds) return;
      const [lo, hi] = this.bounds;
      const c = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]];
      const size = Math.max(hi[0] - lo[0], hi[1] - lo[1], 1);
      const cam = this.viewer.camera;
      if (top) cam.position.set(c[0], c[1] - 0.001, c[2] + size * 1.0);
      else cam.position.set(c[0], c[1] - size * 0.8, c[2] + size * 0.7);
      this.viewer.controls.target.set(c[0], c[1], c[2]);
      this.viewer.controls.update();
      this.viewer.set_dirty();
    }
    material(color, opts) {
      return new THREE.MeshLambertMaterial(Object.assign({ color: new THREE.Color(color) }, opts || {}));
    }
    ensureAgent(a) {
      let o = this.agents.get(a.id);
      if (o) return o;
      const s = this.scale;
      const group = new THREE.Group();
      const cone = new THREE.Mesh(new THREE.ConeGeometry(0.55 * s, 1.6 * s, 16), this.material(a.color, { emissive: new THREE.Color(a.color).multiplyScalar(0.35) }));
      cone.rotation.z = -Math.PI / 2;            // the tip along +x: the heading
      group.add(cone);
      const ring = new THREE.Mesh(new THREE.TorusGeometry(0.9 * s, 0.12 * s, 6, 24), this.material("#ffffff", { emissive: new THREE.Color("#444") }));
      ring.visible = false;
      group.add(ring);
      group.userData.pick = ["agent", a.id];
      this.viewer.set_object(["btm", "agents", a.id], group);
      const trail = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: a.color, transparent: true, opacity: 0.75 }));
      this.viewer.set_object(["btm", "trails", a.id], trail);
      const route = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineDashedMaterial({ color: a.color, dashSize: 1.2 * s, gapSize: 0.8 * s }));
      this.viewer.set_object(["btm", "routes", a.id], route);
      o = { group, ring, trail, route, routeT: null, trailKey: "" };
      this.agents.set(a.id, o);
      this.label("a:" + a.id, a.id, "agent", a.color);
      return o;
    }
    ensureTask(task) {
      let o = this.tasks.get(task.id);
      if (o) return o;
      const s = this.scale;
      const group = new THREE.Group();
      const pts = this.model.taskPoints(task);
      const mat = this.material("#ffffff", { transparent: true, opacity: 0.9 });
      pts.forEach(([name, p], k) => {
        const m = new THREE.Mesh(new THREE.OctahedronGeometry((k ? 0.6 : 0.9) * s), mat);
        m.position.set(p[0], p[1], p[2]);
        group.add(m);
      });
      if (pts.length > 1) {
        const g = new THREE.BufferGeometry().setFromPoints(pts.map(([, p]) => new THREE.Vector3(p[0], p[1], p[2])));
        group.add(new THREE.Line(g, new THREE.LineDashedMaterial({ color: "#9ca3af", dashSize: s, gapSize: s })).computeLineDistances());
      }
      group.userData.pick = ["task", task.id];
      this.viewer.set_object(["btm", "tasks", task.id], group);
      o = { group, mat, at: pts.length ? pts[0][1] : null, state: "" };
      this.tasks.set(task.id, o);
      if (o.at) this.label("t:" + task.id, task.id, "task", "#e5e7eb");
      return o;
    }
    label(key, text, cls, color) {
      const el = document.createElement("div");
      el.className = "label " + cls;
      el.textContent = text;
      el.style.color = color;
      el.dataset.key = key;
      $("labels").appendChild(el);
      this.labels.set(key, { el, p: null });
    }
    update(t) {
      const m = this.model;
      for (const a of m.agents.values()) {
        const o = this.ensureAgent(a);
        const pose = a.poseAt(t);
        o.group.visible = !!pose;
        const lab = this.labels.get("a:" + a.id);
        if (!pose) { lab.p = null; continue; }
        const M = new THREE.Matrix4().makeRotationZ(pose.yaw);
        M.setPosition(pose.x, pose.y, pose.z);
        this.viewer.set_transform(["btm", "agents", a.id], M.toArray());
        o.ring.visible = this.selected === a.id;
        lab.p = [pose.x, pose.y, pose.z];
        lab.el.style.opacity = lastAt(a.lost, t) ? 0.45 : 1;
        // trail: the last TRAIL_S seconds, redrawn when T moved by a pose
        const key = bisect(a.pt, t) + ":" + bisect(a.pt, t - TRAIL_S);
        o.trail.visible = this.options.trails;
        if (this.options.trails && key !== o.trailKey) {
          o.trailKey = key;
          const pts = a.trail(t - TRAIL_S, t);
          pts.push(pose.x, pose.y, pose.z);
          o.trail.geometry.dispose();
          o.trail.geometry = new THREE.BufferGeometry();
          o.trail.geometry.setAttribute("position", new THREE.Float32BufferAttribute(pts, 3));
        }
        const route = lastAt(a.routes, t);
        const cur = lastAt(a.tasks, t);
        const showRoute = this.options.routes && route && (cur ? cur[1] !== null || route[0] >= cur[0] : true);
        o.route.visible = !!showRoute;
        if (showRoute && o.routeT !== route[0]) {
          o.routeT = route[0];
          o.route.geometry.dispose();
          o.route.geometry = new THREE.BufferGeometry().setFromPoints(route[1].map((p) => new THREE.Vector3(p[0], p[1], p[2])));
          o.route.computeLineDistances();
        }
      }
      for (const task of m.tasks.values()) {
        const o = this.ensureTask(task);
        const st = m.taskState(task, t);
        const lab = this.labels.get("t:" + task.id);
        o.group.visible = !!st;
        if (lab) lab.p = st && o.at ? o.at : null;
        if (!st) continue;
        if (o.state !== st[1]) {
          o.state = st[1];
          o.mat.color.set(TASK_COLORS[st[1]] || "#ffffff");
          o.mat.emissive = new THREE.Color(TASK_COLORS[st[1]] || "#ffffff").multiplyScalar(0.3);
          if (lab) lab.el.style.color = TASK_COLORS[st[1]] || "#e5e7eb";
        }
      }
      this.viewer.set_dirty();
    }
    afterRender() {              // the HTML labels follow the 3D points they name
      const show = this.options.labels;
      const cam = this.viewer.camera;
      const w = this.pane.offsetWidth, h = this.pane.offsetHeight;
      const v = new THREE.Vector3();
      for (const { el, p } of this.labels.values()) {
        if (!show || !p) { el.style.display = "none"; continue; }
        v.set(p[0], p[1], p[2]).project(cam);
        if (v.z > 1 || v.z < -1) { el.style.display = "none"; continue; }
        el.style.display = "block";
        el.style.left = ((v.x + 1) / 2 * w).toFixed(1) + "px";
        el.style.top = ((1 - v.y) / 2 * h).toFixed(1) + "px";
      }
    }
    screenPos(p) {               // pixel position of a world point in the pane (tests, labels)
      const v = new THREE.Vector3(p[0], p[1], p[2]);
      this.viewer.camera.updateMatrixWorld();
      v.project(this.viewer.camera);
      return [(v.x + 1) / 2 * this.pane.offsetWidth, (1 - v.y) / 2 * this.pane.offsetHeight, v.z];
    }
    worldScreen(p) {             // a world point in page coordinates (tests)
      const r = this.pane.getBoundingClientRect();
      const [x, y] = this.screenPos(p);
      return [r.left + x, r.top + y];
    }
    ray(cx, cy) {                // the camera ray through a page point
      const r = this.pane.getBoundingClientRect();
      const ndc = new THREE.Vector2((cx - r.left) / r.width * 2 - 1, -(cy - r.top) / r.height * 2 + 1);
      const ray = new THREE.Raycaster();
      this.viewer.camera.updateMatrixWorld();
      ray.setFromCamera(ndc, this.viewer.camera);
      return ray;
    }
    hasRock() {                  // the map has a rock surface (scene.py's /mine)
      const node = this.viewer.scene_tree.children.mine;
      let found = false;
      if (node) node.object.traverse((o) => { if (o.isMesh) found = true; });
      return found;
    }
    surfacePick(cx, cy) {        // the mine's surface under a page point: {p, normal}, world frame
      const r = this.pane.getBoundingClientRect();
      if (cx < r.left || cx >= r.right || cy < r.top || cy >= r.bottom) return null;
      const ray = this.ray(cx, cy);
      if (this.hasRock()) {      // front faces only, so the cut-away near rock is not hit; a
        const obj = this.viewer.scene_tree.children.mine.object;   // miss is solid rock: null
        obj.updateMatrixWorld(true);
        const hit = ray.intersectObject(obj, true).find((h) => h.face);
        if (!hit) return null;
        const n = hit.face.normal.clone().applyMatrix3(new THREE.Matrix3().getNormalMatrix(hit.object.matrixWorld)).normalize();
        return { p: [hit.point.x, hit.point.y, hit.point.z], normal: [n.x, n.y, n.z] };
      }
      if (!this.bounds) return null;   // a map without rock: its floor (it stands on it)
      const [lo, hi] = this.bounds;
      const p = ray.ray.intersectPlane(new THREE.Plane(new THREE.Vector3(0, 0, 1), -lo[2]), new THREE.Vector3());
      if (!p || p.x < lo[0] || p.x > hi[0] || p.y < lo[1] || p.y > hi[1]) return null;
      return { p: [p.x, p.y, p.z], normal: [0, 0, 1] };
    }
    setMark(key, p, surface, text, color) {   // a picked point (null: hide it)
      let o = this.marks.get(key);
      if (!p) {
        if (o) { o.group.visible = false; this.labels.get("m:" + key).p = null; this.viewer.set_dirty(); }
        return;
      }
      if (!o) {
        const s = this.scale;
        const group = new THREE.Group();
        const mat = new THREE.MeshBasicMaterial({ color: new THREE.Color(color), depthTest: false, transparent: true, opacity: 0.95 });
        const ball = new THREE.Mesh(new THREE.SphereGeometry(0.45 * s, 16, 12), mat);
        ball.renderOrder = 10;
        const ring = new THREE.Mesh(new THREE.TorusGeometry(1.0 * s, 0.09 * s, 6, 32), mat);
        ring.renderOrder = 10;
        const stem = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: new THREE.Color(color), depthTest: false }));
        stem.renderOrder = 10;
        group.add(ball, ring, stem);
        this.viewer.set_object(["btm", "console", key], group);
        o = { group, ball, ring, stem };
        this.marks.set(key, o);
        this.label("m:" + key, "", "mark", color);   // a ring of fixed size on the page, and the name
        const el = this.labels.get("m:" + key).el;
        el.innerHTML = '<i></i><span></span>';
        el.style.setProperty("--mark", color);
      }
      o.group.visible = true;
      o.ball.position.set(p[0], p[1], p[2]);
      o.ring.position.set(p[0], p[1], p[2]);
      const from = surface || p;
      o.stem.geometry.dispose();
      o.stem.geometry = new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(...from), new THREE.Vector3(...p)]);
      const lab = this.labels.get("m:" + key);
      lab.p = p; lab.el.lastChild.textContent = text;
      this.viewer.set_dirty();
    }
    pick(cx, cy) {               // the agent or task under a click (meshcat's camera ray)
      const ray = this.ray(cx, cy);
      const targets = [...this.agents.values()].map((o) => o.group).concat([...this.tasks.values()].map((o) => o.group));
      for (const hit of ray.intersectObjects(targets.filter((g) => g.visible), true)) {
        let o = hit.object;
        while (o && !o.userData.pick) o = o.parent;
        if (o && this.onPick) { this.onPick(o.userData.pick[0], o.userData.pick[1]); return; }
      }
    }
    setRisk(on) { this.viewer.set_property(["risk"], "visible", on); this.viewer.set_dirty(); }
    setLidar(points) {
      if (!points || !points.length) { if (this.lidar) this.lidar.visible = false; this.viewer.set_dirty(); return; }
      const g = new THREE.BufferGeometry();
      g.setAttribute("position", new THREE.Float32BufferAttribute(points, 3));
      const obj = new THREE.Points(g, new THREE.PointsMaterial({ color: "#22d3ee", size: 0.12 * this.scale }));
      this.viewer.set_object(["btm", "lidar"], obj);
      this.lidar = obj;
      this.viewer.set_dirty();
    }
  }

  // ------------------------------------------------------------------------ the tree panel
  class TreePanel {
    constructor(el) { this.el = el; this.agent = null; this.nodes = null; this.items = []; this.shown = []; }
    show(agent) {
      if (this.agent === agent && this.nodes === (agent && agent.nodes)) return;
      this.agent = agent; this.nodes = agent ? agent.nodes : null;
      this.el.textContent = "";
      this.items = []; this.shown = [];
      if (!this.nodes) { this.el.innerHTML = '<p class="muted" style="padding:6px 10px">No tree yet: its first tree event has not arrived (logs before version 2 have none).</p>'; return; }
      const root = document.createElement("ul");
      const lists = [];
      this.depth = [];
      this.nodes.forEach(([name, parent, kind], uid) => {
        const li = document.createElement("li");
        li.dataset.uid = uid;
        const row = document.createElement("span");
        row.className = "bt kind-" + kind + " st-INVALID";
        row.dataset.uid = uid;
        row.title = `${name} (${kind})`;
        const caret = document.createElement("span"); caret.className = "caret";
        const glyph = document.createElement("span"); glyph.className = "glyph"; glyph.textContent = GLYPH[kind] || "•";
        const label = document.createElement("span"); label.className = "name"; label.textContent = name;
        row.append(caret, glyph, label);
        li.appendChild(row);
        (parent >= 0 ? lists[parent] : root).appendChild(li);
        this.depth.push(parent >= 0 ? this.depth[parent] + 1 : 0);
        this.items.push({ li, row, caret, kids: null });
        if (parent >= 0 && !lists[parent].parentElement) {
          this.items[parent].li.appendChild(lists[parent]);
          this.items[parent].caret.textContent = "▾";
        }
        lists.push(document.createElement("ul"));
        this.shown.push("INVALID");
      });
      this.items.forEach((it, uid) => {
        it.caret.onclick = () => { it.li.classList.toggle("collapsed"); this.syncCaret(uid); $("opt-follow").checked = false; };
      });
      this.el.appendChild(root);
      if (this.nodes.length > 40) this.collapseBelow(2);
    }
    syncCaret(uid) {
      const it = this.items[uid];
      if (it.caret.textContent) it.caret.textContent = it.li.classList.contains("collapsed") ? "▸" : "▾";
    }
    setAll(collapsed) { this.items.forEach((it, uid) => { it.li.classList.toggle("collapsed", collapsed && uid > 0); this.syncCaret(uid); }); }
    collapseBelow(d) { this.items.forEach((it, uid) => { it.li.classList.toggle("collapsed", this.depth[uid] >= d); this.syncCaret(uid); }); }
    update(status, follow) {
      if (!this.nodes || !status) return;
      for (let uid = 0; uid < status.length; uid++) {
        if (this.shown[uid] !== status[uid]) {
          const it = this.items[uid];
          it.row.classList.remove("st-" + this.shown[uid]);
          it.row.classList.add("st-" + status[uid]);
          this.shown[uid] = status[uid];
        }
      }
      if (follow) {             // open the branches with an active node; fold the idle ones
        const active = status.map((s) => s !== "INVALID");
        for (let uid = status.length - 1; uid > 0; uid--) {
          if (active[uid]) active[this.nodes[uid][1]] = true;
        }
        const running = status.map((s) => s === "RUNNING");
        for (let uid = status.length - 1; uid > 0; uid--) {
          if (running[uid]) running[this.nodes[uid][1]] = true;
        }
        this.items.forEach((it, uid) => {
          if (!it.caret.textContent || uid === 0) return;
          const fold = this.nodes.length > 40 ? !running[uid] : !active[uid];
          if (it.li.classList.contains("collapsed") !== fold) { it.li.classList.toggle("collapsed", fold); this.syncCaret(uid); }
        });
      }
    }
  }

  // ------------------------------------------------------------------------ the page
  const model = new Model();
  const state = { viewT: 0, follow: true, playing: false, speed: 5, live: false, complete: false, gone: false,
    selected: null, task: null, lastPanel: 0, drawnVersion: -1, drawnT: -1, info: null, lidarOn: false, lidarKey: "" };
  const scene = new Scene3D($("meshcat-pane"), model);
  const tree = new TreePanel($("tree"));
  const fmt = (t) => (t === null || t === undefined ? "" : Number(t).toFixed(1));
  const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));

  function legend() {
    $("legend").innerHTML = Object.entries(TASK_COLORS).map(([k, c]) => `<span><i style="background:${c}"></i>${k}</span>`).join("");
  }

  function selectAgent(id) {
    state.selected = id;
    scene.selected = id;
    state.lidarKey = "";
    for (const b of $("agent-tabs").children) b.classList.toggle("on", b.dataset.agent === id);
    state.drawnT = -1;
  }

  function agentTabs() {
    const tabs = $("agent-tabs");
    if (tabs.children.length === model.agents.size) return;
    tabs.textContent = "";
    for (const a of model.agents.values()) {
      const b = document.createElement("button");
      b.dataset.agent = a.id;
      b.innerHTML = `<i style="background:${a.color}"></i>${esc(a.id)}`;
      b.onclick = () => selectAgent(a.id);
      tabs.appendChild(b);
    }
    if (!state.selected && model.agents.size) selectAgent(model.agents.keys().next().value);
    else selectAgent(state.selected);
    if (ops.cfg) tabMarks();
  }

  function panels(t) {
    agentTabs();
    const counts = {};
    const rows = [];
    for (const task of model.tasks.values()) {
      const st = model.taskState(task, t);
      if (!st) continue;
      counts[st[1]] = (counts[st[1]] || 0) + 1;
      const done = task.states.find((s) => s[1] === "done" && s[0] <= t);
      const color = TASK_COLORS[st[1]] || "#fff";
      const live = ops.cfg && opsTaskOpen(task);   // the console's controls: on what is not over
      rows.push(`<tr data-task="${esc(task.id)}" data-state="${esc(st[1])}"${state.task === task.id ? ' class="picked"' : ""}><td>${esc(task.id)}</td><td>${esc(task.type)}</td>` +
        `<td><span class="state" style="background:${color}">${esc(st[1])}</span></td><td>${esc(st[2] || "")}</td>` +
        `<td>${live ? prioritySelect(task) : task.priority === undefined || task.priority === null ? "" : esc(task.priority)}</td><td>${fmt(task.added)}</td>` +
        `<td>${done ? fmt(done[0]) : ""}</td><td class="muted">${esc(st[3] || "")}</td>` +
        (ops.cfg ? `<td class="ops">${live ? `<button class="cancel-task" data-task="${esc(task.id)}" title="Cancel ${esc(task.id)}"${ops.closed ? " disabled" : ""}>✕</button>` : ""}</td>` : "") + "</tr>");
    }
    const body = $("tasks").tBodies[0], html = rows.join("");
    // rewritten only when it changed, and never under the operator's hand (an open menu)
    if (html !== state.tasksHtml && !body.contains(document.activeElement)) { body.innerHTML = html; state.tasksHtml = html; }
    $("counts").innerHTML = Object.entries(counts).map(([k, n]) => `<span style="color:${TASK_COLORS[k] || "#fff"}">${k} ${n}</span>`).join("");
    // the selected agent: action, task, mode; its tree and blackboard
    const a = state.selected ? model.agents.get(state.selected) : null;
    if (a) {
      const pose = a.poseAt(t), stage = lastAt(a.stages, t), cur = lastAt(a.tasks, t), lost = lastAt(a.lost, t);
      $("agent-text").innerHTML = `<b>${esc(a.id)}</b> · task <b>${esc(cur && cur[1] ? cur[1] : "—")}</b> · action <b>${esc(stage ? stage[1] : "—")}</b>` +
        (pose ? `<br>mode ${esc(pose.mode || "?")} · (${pose.x.toFixed(1)}, ${pose.y.toFixed(1)}, ${pose.z.toFixed(1)}) m` : "") +
        (lost ? `<br><span style="color:var(--failure)">lost: ${esc(lost[1])}</span>` : "");
      tree.show(a);
      const c = a.treeAt(t);
      tree.update(c ? c.status : null, $("opt-follow").checked);
      const bb = c ? [...c.bb.entries()].sort() : [];
      $("blackboard").tBodies[0].innerHTML = bb.map(([k, v]) =>
        `<tr class="${t - (c.changedAt.get(k) || -99) < 1 ? "changed" : ""}"><td>${esc(k)}</td><td>${esc(JSON.stringify(v))}</td></tr>`).join("") ||
        '<tr><td class="muted">(empty)</td><td></td></tr>';
    }
    agentActions();
    if ($("tab-timeline").classList.contains("active")) timeline(t);
    if ($("tab-events").classList.contains("active")) {
      const i = bisect(model.events.tsCache || [], t);
      const out = [];
      for (let k = i; k >= 0 && out.length < 300; k--) {
        const [et, text, warn] = model.events[k];
        out.push(`<li class="${warn ? "warn" : ""}"><span class="muted">${fmt(et)}</span> ${esc(text)}</li>`);
      }
      $("events").innerHTML = out.join("");
    }
  }

  function timeline(t) {
    const svg = $("timeline");
    const W = svg.clientWidth || 800, left = 60, right = 12, rowH = 18;
    const agents = [...model.agents.values()];
    const H = Math.max(60, 24 + agents.length * rowH);
    svg.setAttribute("height", H);
    const span = Math.max(model.tEnd, t, 1);
    const x = (tt) => left + (W - left - right) * tt / span;
    const parts = [];
    agents.forEach((a, i) => {
      const y = 6 + i * rowH;
      parts.push(`<text x="4" y="${y + 12}">${esc(a.id)}</text>`);
      for (let k = 0; k < a.tasks.length; k++) {
        const [t0, task] = a.tasks[k];
        if (!task || t0 > t) continue;
        const t1 = Math.min(k + 1 < a.tasks.length ? a.tasks[k + 1][0] : t, t);
        parts.push(`<rect x="${x(t0)}" y="${y}" width="${Math.max(1, x(t1) - x(t0))}" height="${rowH - 4}" rx="3" fill="${a.color}" opacity="0.8"><title>${esc(task)} ${fmt(t0)}–${fmt(t1)} s</title></rect>`);
        if (x(t1) - x(t0) > 24) parts.push(`<text x="${x(t0) + 3}" y="${y + 11}" fill="#111" style="fill:#111">${esc(task)}</text>`);
      }
    });
    for (const task of model.tasks.values()) {
      if (task.added > t) continue;
      parts.push(`<line x1="${x(task.added)}" x2="${x(task.added)}" y1="${H - 14}" y2="${H - 8}" stroke="#9ca3af"><title>${esc(task.id)} added at ${fmt(task.added)} s</title></line>`);
    }
    const step = Math.pow(10, Math.floor(Math.log10(span / 5 || 1)));
    const tick = span / step > 10 ? step * 2 : step;
    for (let tt = 0; tt <= span; tt += tick) parts.push(`<text class="axis" x="${x(tt)}" y="${H - 1}">${Math.round(tt)}</text>`);
    parts.push(`<line x1="${x(t)}" x2="${x(t)}" y1="0" y2="${H}" stroke="#f43f5e" stroke-width="2"/>`);
    svg.innerHTML = parts.join("");
    svg.onclick = (e) => {
      const r = svg.getBoundingClientRect();
      seek(Math.max(0, Math.min(span, (e.clientX - r.left - left) / (W - left - right) * span)));
    };
  }

  function seek(t) {
    state.viewT = t;
    state.follow = false;
    refreshControls();
  }

  function refreshControls() {
    const slider = $("slider");
    slider.max = model.tEnd.toFixed(1);
    if (document.activeElement !== slider) slider.value = state.viewT.toFixed(1);
    $("slider-time").textContent = `${fmt(state.viewT)} / ${fmt(model.tEnd)} s`;
    $("btn-play").textContent = state.playing ? "❚❚" : "▶";
    $("btn-live").style.display = state.live ? "" : "none";
    $("btn-live").classList.toggle("on", state.follow);
    const mode = $("mode");
    const ended = state.live && (state.complete || state.gone);
    mode.textContent = state.live ? (ended ? "ENDED" : "LIVE") : "REPLAY";
    mode.className = "badge " + (state.live ? (ended ? "ended" : "live") : "replay");
  }

  function lidar(t) {
    const a = state.selected ? model.agents.get(state.selected) : null;
    if (!state.lidarOn || !a || CFG.embedded) { if (scene.lidar) scene.setLidar(null); return; }
    const p = a.poseAt(t);
    if (!p) return;
    const key = `${a.id}:${p.x.toFixed(1)}:${p.y.toFixed(1)}:${p.z.toFixed(1)}`;
    if (key === state.lidarKey || state.lidarBusy) return;
    state.lidarKey = key; state.lidarBusy = true;
    fetch(`api/scan?x=${p.x}&y=${p.y}&z=${p.z}&yaw=${p.yaw}`, { headers: authHeaders() }).then((r) => r.json()).then((d) => {
      scene.setLidar(d.points);
      document.body.dataset.lidarPoints = d.points.length / 3;
    }).catch(() => {}).finally(() => { state.lidarBusy = false; });
  }

  let lastFrame = performance.now();
  function frame(now) {
    const dt = (now - lastFrame) / 1000;
    lastFrame = now;
    if (state.follow) state.viewT = model.tEnd;
    else if (state.playing) {
      state.viewT = Math.min(model.tEnd, state.viewT + dt * state.speed);
      if (state.viewT >= model.tEnd && (!state.live || state.complete || state.gone)) state.playing = false;
    }
    if (ops.watch.size && model.version !== ops.watchedVersion) { ops.watchedVersion = model.version; watchTasks(); }
    const t = state.viewT;
    if (t !== state.drawnT || model.version !== state.drawnVersion) {
      scene.update(t);
      state.drawnT = t; state.drawnVersion = model.version;
      $("clock").textContent = `t = ${fmt(t)} s`;
      document.body.dataset.viewT = t.toFixed(2);
      if (now - state.lastPanel > PANEL_MS) { state.lastPanel = now; panels(t); refreshControls(); lidar(t); }
      else state.drawnT = -1; // redraw the panels on a later frame
    }
    requestAnimationFrame(frame);
  }

  scene.onPick = (kind, id) => {
    if (kind === "agent") selectAgent(id);
    else {
      state.task = id;
      state.drawnT = -1;
      requestAnimationFrame(() => {
        const row = document.querySelector(`#tasks tr[data-task="${CSS.escape(id)}"]`);
        if (row) row.scrollIntoView({ block: "nearest" });
      });
    }
    document.body.dataset.picked = `${kind}:${id}`;
  };

  // ------------------------------------------------------------------------ the operator console
  // A live run served with a console (info.console.enabled: `btmission run --console`): add a
  // task where the map is clicked, cancel one, change its priority, recall an agent, take it out
  // of the auction, pause the allocation, cut a link (simulator drills). Every action's result,
  // and then what happens to the task it touched (from the records), goes to the console log.
  const TOKEN_KEY = "btm-token";
  const OFFSET_M = 1.0;        // a picked task location: this far off the rock face clicked
                               // (unless info.console.pick_offset_m says otherwise)
  const STATUS_MS = 1000;      // api/status is polled this often while the run goes on
  const FINAL = new Set(["done", "failed", "cancelled"]);
  const MARK_COLORS = ["#e879f9", "#22d3ee", "#fde047", "#fb7185"];
  const ESC_HINT = "Esc stops picking";
  const MISS_HINT = "no open space under the cursor: click a tunnel (its floor or a wall)";
  const ops = {
    cfg: null,                 // info.console, when it is enabled
    token: null,
    status: null, agentStatus: new Map(), taskStatus: new Map(),
    arm: null,                 // add mode: null, "*" (the form's first position) or a field name
    points: new Map(),         // position field → {p, surface}: the form's points
    watch: new Map(),          // task id → {since: mission time, seen: its states told}
    shown: [],                 // the form's position fields, in order
    watchedVersion: -1, actionsKey: "", closed: false,
    idEdited: false,           // the operator typed the form's id: a new type keeps it
  };

  function takeToken() {       // ?token=… → this tab's session storage, and out of the address bar
    try {
      const q = new URLSearchParams(location.search);
      const tok = q.get("token");
      if (tok) {
        sessionStorage.setItem(TOKEN_KEY, tok);
        q.delete("token");
        const rest = q.toString();
        history.replaceState(history.state, "", location.pathname + (rest ? "?" + rest : "") + location.hash);
      }
      return sessionStorage.getItem(TOKEN_KEY);
    } catch (e) {
      return null;
    }
  }
  function authHeaders(h) {
    h = h || {};
    if (ops.token) h.Authorization = "Bearer " + ops.token;
    h["X-Btmission-Client"] = "page";  // the server's rate limits count each client apart
    return h;
  }
  function streamQuery() {
    const c = state.info && state.info.console;
    return c && c.token_required && ops.token ? "&token=" + encodeURIComponent(ops.token) : "";
  }

  function logResult(ok, text) {
    const li = document.createElement("li");
    li.dataset.ok = ok ? "1" : "0";
    li.textContent = text;
    const log = $("console-log");
    log.prepend(li);
    while (log.children.length > 200) log.lastChild.remove();
    log.scrollTop = 0;         // the newest, on top, in sight
    document.body.dataset.lastResult = text;
  }
  function errorText(status, data, retry) {
    let m = data && typeof data.message === "string" ? data.message : "";
    if (!m && data && typeof data.detail === "string") m = data.detail;
    if (!m && data && Array.isArray(data.detail)) {
      m = data.detail.map((d) => `${(d.loc || []).filter((x) => x !== "body").join(".")}: ${d.msg}`).join("; ");
    }
    if (!m) m = `the server answered ${status}`;
    if (status === 429 && retry) m += ` (try again in ${retry} s)`;
    return m;
  }
  async function request(method, path, body) {
    const headers = authHeaders({ "X-Btmission-Client": "page" });
    if (body !== undefined) headers["Content-Type"] = "application/json";
    let r;
    try {
      r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    } catch (e) {
      return { ok: false, status: 0, data: {}, message: "the viewer's server did not answer (has the run's process stopped?)" };
    }
    let data = {};
    try { data = await r.json(); } catch (e) { data = {}; }
    if (r.ok) return { ok: true, status: r.status, data, message: data.message || `${data.command || method} ok` };
    let message = errorText(r.status, data, r.headers.get("Retry-After"));
    if (r.status === 401 || r.status === 403) { message = tokenText(message); askToken(message); }
    return { ok: false, status: r.status, data, message };
  }
  async function act(method, path, body, task) {   // one action; its result goes to the log
    const sent = model.tEnd;
    const res = await request(method, path, body);
    logResult(res.ok, res.message);
    // its states from the step that applied the command (the answer's t, rounded to 1 ms)
    if (res.ok && task) watchTask(task, typeof res.data.t === "number" ? res.data.t - 0.01 : sent);
    pollStatus();
    return res;
  }

  // what happens to the tasks the console touched, told as the records bring it
  function watchTask(id, since) {   // its states from mission time `since` on
    ops.watch.set(id, { since, seen: 0 });
    ops.watchedVersion = -1;
  }
  function taskNews(id, st, prev) {
    const [t, s, agent, note] = st;
    const at = `at ${fmt(t)} s`;
    if (prev && prev[1] === s && prev[2] === agent) return null;
    switch (s) {
      case "open": return prev ? `${id} back in the pool ${at}${note ? ": " + note : ""}` : null;
      case "assigned": return `${id} assigned to ${agent} ${at}`;
      case "committed": return `${id}: ${agent} committed ${at}`;
      case "done": return `${id} done by ${agent} ${at}`;
      case "unreachable": return `${id} unreachable: ${note || "no agent can reach it"}`;
      case "failed": return `${id} failed${agent ? " (" + agent + ")" : ""} ${at}${note ? ": " + note : ""}`;
      case "cancelled": return `${id} cancelled ${at}`;
      default: return `${id} ${s} ${at}`;
    }
  }
  function watchTasks() {
    for (const [id, w] of ops.watch) {
      const task = model.tasks.get(id);
      if (!task) continue;
      let k = w.seen;
      for (; k < task.states.length; k++) {
        const st = task.states[k];
        if (st[0] < w.since) continue;
        const text = taskNews(id, st, k ? task.states[k - 1] : null);
        // (the command's own answer may have said it already: "T4 cancelled at 137.0 s")
        if (text && text !== document.body.dataset.lastResult) logResult(st[1] !== "unreachable" && st[1] !== "failed", text);
      }
      w.seen = k;
      if (k && FINAL.has(task.states[k - 1][1])) ops.watch.delete(id);
    }
  }

  // ---- the task table's controls
  function opsTaskOpen(task) { // not over at the run's newest time
    const st = task.states[task.states.length - 1];
    return !!st && !FINAL.has(st[1]);
  }
  function priorityLabel(name, m) { return `${esc(name)} (×${esc(m)})`; }   // the form's and the table's
  function prioritySelect(task) {
    const tt = (ops.cfg.task_types || {})[task.type] || {};
    const base = Number(tt.priority) || 1;
    const s = ops.taskStatus.get(task.id);
    const p = Number(s && s.priority !== undefined ? s.priority : task.priority);
    let found = false;
    const opts = Object.entries(ops.cfg.priorities || {}).map(([name, m]) => {
      const sel = !found && Math.abs(base * m - p) <= 1e-6 * Math.max(1, Math.abs(p));
      found = found || sel;
      return `<option value="${esc(name)}"${sel ? " selected" : ""}>${priorityLabel(name, m)}</option>`;
    });
    if (!found) opts.unshift(`<option value="" selected disabled>${esc(Number.isFinite(p) ? +p.toFixed(3) : "?")}</option>`);
    const now = Number.isFinite(p) ? ` (now ${+p.toFixed(3)}: the type's ${+base.toFixed(3)} × the level)` : "";
    return `<select class="task-priority" data-task="${esc(task.id)}" title="Change ${esc(task.id)}'s priority${now}"${ops.closed ? " disabled" : ""}>${opts.join("")}</select>`;
  }

  // ---- the selected agent's controls
  function agentActions() {
    const el = $("agent-actions");
    if (!ops.cfg || !state.selected) { el.hidden = true; return; }
    const id = state.selected, s = ops.agentStatus.get(id) || {};
    const key = JSON.stringify([id, s.alive, s.link_up, s.recalled, s.excluded, ops.closed]);
    if (key === ops.actionsKey) return;
    ops.actionsKey = key;
    el.hidden = false;
    const off = ops.closed || s.alive === false ? " disabled" : "";
    const chips = [[s.alive === false, "not running"], [s.recalled, "recalled"], [s.excluded, "excluded"], [s.link_up === false, "link down"]]
      .filter(([on]) => on).map(([, text]) => `<span class="chip">${text}</span>`);
    el.innerHTML =
      `<button id="btn-recall" data-act="recall"${off || (s.recalled ? " disabled" : "")} title="${esc(id)} gives up its task, stops bidding and runs its default behaviour (home)">⌂ Recall</button>` +
      (s.excluded || s.recalled   // (include brings a recalled agent back too)
        ? `<button id="btn-exclude" data-act="include"${off} title="${esc(id)} bids for tasks again${s.recalled ? " (and leaves its default behaviour when it wins one)" : ""}">Include</button>`
        : `<button id="btn-exclude" data-act="exclude"${off} title="Take ${esc(id)} out of the auction: it wins no new task">Exclude</button>`) +
      (ops.cfg.link_drills && (!ops.cfg.drill_agents || ops.cfg.drill_agents.includes(id))
        ? (s.link_up === false
          ? `<button id="btn-link" data-act="link" data-up="1"${off} title="Drill: restore ${esc(id)}'s link to the coordinator">Restore link</button>`
          : `<button id="btn-link" data-act="link" data-up="0"${off} title="Drill (simulator): cut ${esc(id)}'s link to the coordinator">Cut link</button>`)
        : "") + chips.join("");
  }

  // ---- status: what the records do not carry (pause, exclusion, links)
  async function pollStatus() {
    if (!ops.cfg) return;
    let r;
    try { r = await fetch("api/status", { headers: authHeaders() }); } catch (e) {
      if ((await serverAnswers()) === "refused") serverGone();   // (not a passing network error)
      return;
    }
    if (r.status === 401 || r.status === 403) {
      const m = tokenText(errorText(r.status, await r.json().catch(() => ({}))));
      if (document.body.dataset.lastResult !== m) logResult(false, m);   // (once, not every poll)
      askToken(m);
      return;
    }
    if (!r.ok) return;
    const s = await r.json().catch(() => null);
    if (s) applyStatus(s);
  }
  function statusLoop() {
    pollStatus().finally(() => { if (!ops.closed && !state.gone) setTimeout(statusLoop, STATUS_MS); });
  }
  function applyStatus(s) {
    ops.status = s;
    ops.agentStatus = new Map((s.agents || []).map((a) => [a.id, a]));
    ops.taskStatus = new Map((s.tasks || []).map((t) => [t.id, t]));
    const paused = !!(s.allocation && s.allocation.paused);
    const b = $("btn-pause");
    b.textContent = paused ? "Resume allocation" : "Pause allocation";
    b.classList.toggle("warn", paused);
    $("console-state").textContent = paused ? "allocation paused" : "";
    tabMarks();
    if (s.ended) closeConsole();
    state.drawnT = -1;
  }
  function tabMarks() {         // out of the auction (excluded or recalled): dashed; link down: red ring
    for (const tab of $("agent-tabs").children) {
      const a = ops.agentStatus.get(tab.dataset.agent) || {};
      tab.classList.toggle("out", !!a.excluded || !!a.recalled);
      tab.classList.toggle("nolink", a.link_up === false);
      tab.title = a.recalled ? `${tab.dataset.agent}: recalled (out of the auction)` : a.excluded ? `${tab.dataset.agent}: excluded (out of the auction)` : "";
    }
  }
  function closeConsole(why) {   // the run has ended (or its server has gone): nothing more to command
    if (ops.closed || !ops.cfg) return;
    ops.closed = true;
    disarm();
    for (const id of ["btn-add-task", "btn-pause", "task-form-submit"]) $(id).disabled = true;
    $("console-state").textContent = why ? "server gone" : "run ended";
    logResult(!why, why || "the run has ended: the console takes no more commands");
    state.tasksHtml = ""; ops.actionsKey = ""; state.drawnT = -1;
  }

  // ---- the token
  function tokenText(message) {   // a refusal for the token, and what to do about it
    return /token field/.test(message) ? message : `${message} — paste it in the token field`;
  }
  function askToken(message) {
    const f = $("token-form");
    f.hidden = false;
    f.title = message || "This console needs the token printed on the terminal (the URL's ?token=…)";
    $("token-input").classList.toggle("bad", !!message);
  }

  // ---- add a task: pick the map, fill the form
  function typeInfo(type) { return ((ops.cfg && ops.cfg.task_types) || {})[type] || { fields: [], positions: [] }; }
  function formEl() { return $("task-form"); }
  function arm(field) {
    ops.arm = field;
    $("view3d").classList.add("arming");
    $("btn-add-task").classList.add("on");
    hint(field === "*" ? `Click the map where the task goes · ${ESC_HINT}` : `Click the map: ${field} · ${ESC_HINT}`);
  }
  function disarm() {
    ops.arm = null;
    $("pick-note").hidden = true;
    $("view3d").classList.remove("arming");
    $("btn-add-task").classList.remove("on");
    hint(null);
  }
  function hint(text, warn) { const h = $("pick-hint"); h.hidden = !text; h.textContent = text || ""; h.classList.toggle("warn", !!warn); }
  function note(cx, cy, text) {  // a short note where the map was clicked
    const el = $("pick-note"), r = $("view3d").getBoundingClientRect();
    el.textContent = text;
    el.style.left = (cx - r.left) + "px";
    el.style.top = (cy - r.top) + "px";
    el.hidden = false;
    clearTimeout(ops.noteTimer);
    ops.noteTimer = setTimeout(() => { el.hidden = true; }, 2500);
  }
  function positions() { return typeInfo(formEl().elements.type.value).positions || []; }
  function openForm() {
    const f = formEl();
    if (!f.hidden) return;
    f.hidden = false;
    fold(false);
    ops.idEdited = false;
    proposeId();
    ops.points.clear();
    buildFields();
    formMessage("");
  }
  function proposeId() {       // the type's next free id (P2 for pick_and_deliver, I3 for inspect),
    if (ops.idEdited) return;  // unless the operator wrote one
    const f = formEl(), ids = ops.cfg.next_task_ids || {};
    f.elements.id.value = ids[f.elements.type.value] || ops.cfg.next_task_id || "";
  }
  function fold(on) {         // the form folded to its title (and the hint), the map under it seen
    const f = formEl(), b = $("task-form-fold");
    f.classList.toggle("folded", on);
    b.textContent = on ? "▸" : "▾";
    b.setAttribute("aria-expanded", on ? "false" : "true");
    b.title = on ? "Unfold the form" : "Fold the form to its title (the map under it shows)";
  }
  function closeForm() {
    formEl().hidden = true;
    ops.points.clear();
    showMarks();
    disarm();
    formMessage("");
  }
  function buildFields(previous) {
    const tt = typeInfo(formEl().elements.type.value), pos = new Set(tt.positions || []);
    if (previous) {            // a new type: its positions take the points in the same order
      const kept = previous.map((f) => ops.points.get(f)).filter(Boolean);
      ops.points.clear();
      (tt.positions || []).forEach((f, i) => { if (kept[i]) ops.points.set(f, kept[i]); });
    }
    ops.shown = tt.positions || [];   // (the next type takes these points, in this order)
    $("task-fields").innerHTML = (tt.fields || []).map((f) => pos.has(f)
      ? `<div class="row pos" data-field="${esc(f)}"><span>${esc(f)}</span><span class="xyz">` +
        ["x", "y", "z"].map((c) => `<input type="number" step="0.1" name="${esc(f)}.${c}" placeholder="${c}" aria-label="${esc(f)} ${c} (m)">`).join("") +
        `</span><button type="button" class="pick" data-field="${esc(f)}" title="Pick ${esc(f)} on the map">pick</button></div>`
      : `<label class="row" data-field="${esc(f)}"><span>${esc(f)}</span><input name="${esc(f)}" list="places-list" placeholder="place or number" spellcheck="false"></label>`).join("");
    for (const [f, pt] of ops.points) fillPoint(f, pt.p);
    showMarks();
  }
  function fillPoint(field, p) {
    const f = formEl();
    ["x", "y", "z"].forEach((c, i) => { const el = f.elements[`${field}.${c}`]; if (el) el.value = +p[i].toFixed(1); });
  }
  function setPoint(field, p, surface) {
    ops.points.set(field, { p, surface });
    fillPoint(field, p);
    const row = formEl().querySelector(`.row[data-field="${CSS.escape(field)}"]`);
    if (row) row.classList.remove("bad");
    showMarks();
  }
  function showMarks() {
    const pos = formEl().hidden ? [] : positions();
    const id = formEl().elements.id.value.trim() || "new task";
    pos.forEach((f, k) => {
      const pt = ops.points.get(f);
      scene.setMark(f, pt ? pt.p : null, pt ? pt.surface : null, pos.length > 1 ? `${id} ${f}` : id, MARK_COLORS[k % MARK_COLORS.length]);
    });
    for (const key of scene.marks.keys()) if (!pos.includes(key)) scene.setMark(key, null);
  }
  function formMessage(text, field) {
    const f = formEl();
    $("task-form-msg").textContent = text;
    if (text) fold(false);
    for (const el of f.querySelectorAll(".bad")) el.classList.remove("bad");
    if (!field) return;
    const el = f.querySelector(`.row[data-field="${CSS.escape(field)}"]`) || (f.elements[field] && f.elements[field].closest(".row"));
    if (el) {
      el.classList.add("bad");
      const input = el.querySelector("input, select");
      if (input) input.focus();
    }
  }
  function badField(res) {     // the form field a refusal names: 422's detail[0].loc, or "field: …"
    const f = formEl();
    const known = (name) => typeof name === "string" && (f.elements[name] || f.querySelector(`.row[data-field="${CSS.escape(name)}"]`));
    const d = res.data && res.data.detail;
    if (Array.isArray(d) && d.length && Array.isArray(d[0].loc)) {
      for (let i = d[0].loc.length - 1; i >= 0; i--) if (known(d[0].loc[i])) return d[0].loc[i];
    }
    const m = /^([\w.-]+):/.exec(res.message || "");
    return m && known(m[1]) ? m[1] : null;
  }
  async function submitForm(e) {
    e.preventDefault();
    if (ops.closed) return;
    disarm();                  // (typed coordinates: the click the hint asked for is not needed)
    const f = formEl();
    const type = f.elements.type.value, tt = typeInfo(type), pos = new Set(tt.positions || []);
    const body = { type, priority: f.elements.priority.value };
    const id = f.elements.id.value.trim();
    if (id) body.id = id;
    for (const field of tt.fields || []) {
      if (pos.has(field)) {
        const v = ["x", "y", "z"].map((c) => f.elements[`${field}.${c}`].value.trim());
        if (v.some((x) => x === "" || !Number.isFinite(Number(x)))) {
          formMessage(`${field}: give x, y and z, or pick the point on the map`, field);
          return;
        }
        body[field] = v.map(Number);
      } else {
        const v = f.elements[field].value.trim();
        if (v !== "") body[field] = /^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$/.test(v) ? Number(v) : v;
      }
    }
    formMessage("");
    $("task-form-submit").disabled = true;
    const res = await request("POST", "api/tasks", body);
    $("task-form-submit").disabled = ops.closed;
    logResult(res.ok, res.message);
    if (res.ok) {
      const tid = res.data.task || id;
      if (tid) watchTask(tid, -Infinity);
      closeForm();
      refreshInfo();
    } else {
      formMessage(res.message, badField(res));
    }
    pollStatus();
  }
  async function refreshInfo() {   // the next free task id
    try {
      const res = await fetch("api/console", { headers: authHeaders() });
      if (res.ok) Object.assign(ops.cfg, await res.json());
    } catch (e) { /* the next add proposes the old id; the server says if it is taken */ }
  }
  function pickPoint(cx, cy) {     // Scene3D.onClick: in add mode a click picks the surface
    if (!ops.arm) return false;
    const hit = scene.surfacePick(cx, cy);
    if (!hit) {                    // solid rock (or off the map): nothing is filled
      hint(`${MISS_HINT} · ${ESC_HINT}`, true);
      note(cx, cy, MISS_HINT);
      return true;
    }
    const off = Number.isFinite(ops.cfg.pick_offset_m) ? ops.cfg.pick_offset_m : OFFSET_M;
    const p = hit.p.map((v, i) => Math.round((v + hit.normal[i] * off) * 10) / 10);
    openForm();
    const pos = positions();
    const chain = ops.arm === "*";   // + Task: the type's positions one click after the other
    const field = chain ? pos.find((f) => !ops.points.has(f)) || pos[0] : ops.arm;
    disarm();
    if (field) setPoint(field, p, hit.p);
    const next = chain && pos.find((f) => !ops.points.has(f));
    if (next) arm(next);
    else fold(false);          // every point picked: the form, to check and add
    return true;
  }

  function setupConsole(info) {
    const c = info.console;
    if (CFG.embedded || info.mode !== "live") return;   // a replay, the offline file: no console
    if (!c || !c.enabled) {
      const badge = $("console-ro");
      badge.hidden = false;
      badge.title = (c && c.reason) || "This page only watches the run";
      return;
    }
    ops.cfg = c;
    document.body.classList.add("console-on");
    for (const id of ["console-bar", "btn-add-task", "console-panel", "th-ops"]) $(id).hidden = false;
    const f = formEl();
    f.elements.type.innerHTML = Object.keys(c.task_types || {}).map((t) => `<option value="${esc(t)}">${esc(t)}</option>`).join("");
    f.elements.priority.innerHTML = Object.entries(c.priorities || { normal: 1 })
      .map(([n, m]) => `<option value="${esc(n)}"${n === "normal" ? " selected" : ""}>${priorityLabel(n, m)}</option>`).join("");
    $("places-list").innerHTML = (c.places || []).map((p) => `<option value="${esc(p)}"></option>`).join("");
    if (!ops.token) askToken(null);
    statusLoop();
  }

  function bindConsole() {
    scene.onClick = pickPoint;
    const f = formEl();
    $("btn-add-task").onclick = () => {
      if (ops.arm) { disarm(); return; }
      openForm();
      arm("*");
    };
    f.onsubmit = submitForm;
    $("task-form-cancel").onclick = closeForm;
    $("task-form-close").onclick = closeForm;
    $("task-form-fold").onclick = () => fold(!f.classList.contains("folded"));
    f.elements.type.onchange = () => { proposeId(); buildFields(ops.shown); };
    f.elements.id.oninput = () => { ops.idEdited = f.elements.id.value.trim() !== ""; showMarks(); };
    $("task-fields").addEventListener("click", (e) => {
      const b = e.target.closest("button.pick");
      if (b) arm(b.dataset.field);
    });
    $("task-fields").addEventListener("input", (e) => {
      const row = e.target.closest(".row");
      if (row) row.classList.remove("bad");
      const m = /^(.*)\.([xyz])$/.exec(e.target.name || "");
      if (!m) return;
      const v = ["x", "y", "z"].map((c) => f.elements[`${m[1]}.${c}`].value.trim());
      if (v.every((x) => x !== "" && Number.isFinite(Number(x)))) ops.points.set(m[1], { p: v.map(Number), surface: null });
      else ops.points.delete(m[1]);
      showMarks();
    });
    $("btn-pause").onclick = () => {
      const paused = !!(ops.status && ops.status.allocation && ops.status.allocation.paused);
      act("POST", "api/allocation", { paused: !paused });
    };
    $("token-form").onsubmit = (e) => {
      e.preventDefault();
      const v = $("token-input").value.trim();
      if (!v) return;
      ops.token = v;
      try { sessionStorage.setItem(TOKEN_KEY, v); } catch (err) { /* kept for this page only */ }
      $("token-form").hidden = true;
      $("token-input").value = "";
      if (ops.reloadOnToken) { location.reload(); return; }
      logResult(true, "token set: commands are sent with it");
      pollStatus();
    };
    $("agent-actions").addEventListener("click", (e) => {
      const b = e.target.closest("button[data-act]");
      if (!b || b.disabled || !state.selected) return;
      const what = b.dataset.act;
      act("POST", `api/agents/${encodeURIComponent(state.selected)}/${what}`, what === "link" ? { up: b.dataset.up === "1" } : undefined);
    });
    const body = $("tasks").tBodies[0];
    body.addEventListener("click", (e) => {
      const b = e.target.closest("button.cancel-task");
      if (!b || b.disabled) return;
      b.disabled = true;
      act("DELETE", `api/tasks/${encodeURIComponent(b.dataset.task)}`, undefined, b.dataset.task);
    });
    body.addEventListener("change", (e) => {
      const sel = e.target.closest("select.task-priority");
      if (!sel || !sel.value) return;
      act("PATCH", `api/tasks/${encodeURIComponent(sel.dataset.task)}`, { priority: sel.value }, sel.dataset.task)
        .finally(() => { sel.blur(); state.tasksHtml = ""; state.drawnT = -1; });
    });
    document.addEventListener("keydown", (e) => {
      if (e.key === "Escape" && ops.arm) { e.preventDefault(); disarm(); }
    });
  }

  function bindControls() {
    $("btn-play").onclick = () => {
      if (state.follow) state.follow = false;
      if (!state.playing && state.viewT >= model.tEnd - 1e-6 && (!state.live || state.complete || state.gone)) state.viewT = 0;
      state.playing = !state.playing; refreshControls();
    };
    $("speed").onchange = (e) => { state.speed = Number(e.target.value); };
    $("slider").oninput = (e) => { state.playing = false; seek(Number(e.target.value)); };
    $("btn-live").onclick = () => { state.follow = true; state.playing = false; refreshControls(); };
    $("opt-risk").onchange = (e) => scene.setRisk(e.target.checked);
    $("opt-trails").onchange = (e) => { scene.options.trails = e.target.checked; state.drawnT = -1; };
    $("opt-routes").onchange = (e) => { scene.options.routes = e.target.checked; state.drawnT = -1; };
    $("opt-labels").onchange = (e) => { scene.options.labels = e.target.checked; scene.viewer.set_dirty(); };
    $("opt-lidar").onchange = (e) => { state.lidarOn = e.target.checked; state.lidarKey = ""; state.drawnT = -1; };
    $("btn-fit").onclick = () => scene.fit(false);
    $("btn-top").onclick = () => scene.fit(true);
    $("btn-expand").onclick = () => { $("opt-follow").checked = false; tree.setAll(false); };
    $("btn-collapse").onclick = () => { $("opt-follow").checked = false; tree.setAll(true); };
    for (const b of document.querySelectorAll("#tabs .tab")) {
      b.onclick = () => {
        for (const x of document.querySelectorAll("#tabs .tab")) x.classList.toggle("active", x === b);
        for (const p of document.querySelectorAll(".tabpane")) p.classList.toggle("active", p.id === "tab-" + b.dataset.tab);
        state.drawnT = -1;
      };
    }
    document.addEventListener("keydown", (e) => {
      if (e.code === "Space" && e.target === document.body) { e.preventDefault(); $("btn-play").click(); }
    });
    if (CFG.embedded) {
      const l = $("opt-lidar").parentElement;
      l.classList.add("disabled"); $("opt-lidar").disabled = true;
      l.title = "A LiDAR scan needs the viewer's server: btmission view LOG";
    }
  }

  function start(info) {
    state.info = info;
    state.live = info.mode === "live";
    state.follow = state.live;
    $("mission").textContent = info.mission || "";
    document.title = `${info.mission || "btmission"} · btmission viewer`;
    (info.agents || []).forEach((a) => model.agent(a.id, a.start));
    if (info.scene) scene.setBounds(info.scene.bounds);
    if (!state.live) { state.viewT = 0; state.playing = false; }
    setupConsole(info);
    refreshControls();
  }

  // the server gone for good (the run ended or was stopped without the stream's `complete`
  // reaching the page): said once, the controls disabled, no more reconnecting
  const GONE = "the run's server has gone (the run ended or was stopped)";
  const GONE_AFTER = 3;        // stream errors in a row, the server silent
  function serverGone() {
    if (state.gone || state.complete || CFG.embedded) return;
    state.gone = true;
    if (state.es) state.es.close();
    clearTimeout(state.retry);
    const conn = $("conn");
    conn.textContent = state.live ? GONE : "the viewer's server has gone";
    conn.classList.add("gone");
    document.body.dataset.gone = "1";
    closeConsole(GONE);
    refreshControls();
  }
  async function serverAnswers() {  // "up" (any HTTP answer, even a refusal), "refused" or "silent"
    const ctl = new AbortController(), timer = setTimeout(() => ctl.abort(), 5000);
    try {
      await fetch("api/status", { headers: authHeaders(), cache: "no-store", signal: ctl.signal });
      return "up";
    } catch (e) {
      return e && e.name === "AbortError" ? "silent" : "refused";
    } finally { clearTimeout(timer); }
  }

  function connect(cursor) {
    if (state.gone) return;
    const es = state.es = new EventSource(`api/stream?cursor=${cursor}${streamQuery()}`);
    if (!state.streamFails) $("conn").textContent = "connected";   // (a reconnect: once open)
    es.onopen = () => { state.streamFails = 0; $("conn").textContent = "connected"; };
    es.onmessage = (e) => {
      state.streamFails = 0;
      const msg = JSON.parse(e.data);
      model.add(msg.records);
      if (msg.latest) model.add(msg.latest);
      cursor = msg.cursor;
      document.body.dataset.records = model.count;
    };
    es.addEventListener("complete", () => {
      es.close(); state.complete = true; $("conn").textContent = "";
      document.body.dataset.complete = "1"; refreshControls(); closeConsole();
    });
    es.onerror = async () => {      // reconnect from where we were (not from the start) ...
      es.close();
      if (state.complete || state.gone) return;
      state.streamFails = (state.streamFails || 0) + 1;
      // ... unless the server is gone: it refuses the connection, or it has not answered
      // GONE_AFTER times in a row (a server that answers, e.g. 503 when busy, is retried)
      const up = await serverAnswers();
      if (up === "refused" || (up === "silent" && state.streamFails >= GONE_AFTER)) { serverGone(); return; }
      $("conn").textContent = "reconnecting…";
      state.retry = setTimeout(() => connect(cursor), 1000);
    };
  }

  function b64bytes(b64) {
    const s = atob(b64), out = new Uint8Array(s.length);
    for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out;
  }

  async function main() {
    legend();
    bindControls();
    bindConsole();
    if (CFG.embedded) {
      start(CFG.info);
      if (CFG.scene) scene.loadCommands(b64bytes(CFG.scene).buffer);
      model.add(CFG.records || []);
      state.complete = true;
      document.body.dataset.records = model.count;
      document.body.dataset.complete = "1";
    } else {
      ops.token = takeToken();
      const r = await fetch("api/info", { headers: authHeaders() });   // (off loopback it needs the token)
      if (r.status === 401 || r.status === 403) {
        const refusal = await r.json().catch(() => ({}));
        $("console-bar").hidden = false;
        $("btn-pause").hidden = true;
        ops.reloadOnToken = true;     // with a token, the page starts again
        askToken(tokenText(errorText(r.status, refusal)));
        $("conn").textContent = "this page needs the run's token — paste it in the token field";
        return;
      }
      const info = await r.json();
      start(info);
      const buf = await (await fetch("api/scene", { headers: authHeaders() })).arrayBuffer();
      document.body.dataset.sceneCommands = scene.loadCommands(buf);
      connect(0);
    }
    document.body.dataset.ready = "1";
    requestAnimationFrame(frame);
  }

  window.btm = { model, scene, state, seek, selectAgent, ops,
    surfacePick: (cx, cy) => scene.surfacePick(cx, cy),
    worldScreen: (p) => scene.worldScreen(p),
    agentScreen: (id) => { const p = model.agents.get(id).poseAt(state.viewT); return p ? scene.screenPos([p.x, p.y, p.z]) : null; } };
  main().catch((e) => { $("conn").textContent = "error: " + e; console.error(e); });
})();
