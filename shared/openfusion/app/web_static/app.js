// The OpenFusion-Z query page. Every text from the server or the user is put into the page with
// textContent (never innerHTML), so a label or query can never become markup or script.
import * as THREE from "three";
import { OrbitControls } from "/vendor/three/OrbitControls.js";

const HEALTH_PERIOD_MS = 5000;
const NEEDED_SERVICES = ["geometry", "query"];  // what this page asks; shown as down when absent
const TOP_K = 5;
const $ = (id) => document.getElementById(id);

function setStatus(text, isError = false) {
  const status = $("status");
  status.textContent = text;
  status.classList.toggle("error", isError);
}

async function getJson(url) {
  const response = await fetch(url, { headers: { Accept: "application/json" } });
  let data = null;
  try {
    data = await response.json();
  } catch (err) {
    throw new Error(`${url}: the server answered ${response.status} without JSON`);
  }
  if (!response.ok) throw new Error(data && typeof data.error === "string" ? data.error : `HTTP ${response.status}`);
  return data;
}

function fixed(value, digits) {
  return typeof value === "number" && Number.isFinite(value) ? value.toFixed(digits) : "–";
}

function shown(value) {
  if (value === undefined || value === null) return "–";
  if (typeof value === "number") return fixed(value, 3);
  if (typeof value === "object") return JSON.stringify(value);
  return String(value);
}

// ------------------------------------------------------------------------------- 3D view

class MapView {
  constructor(element) {
    this.element = element;
    this.keys = new Int32Array(0);
    this.baseColors = new Float32Array(0);
    this.highlight = null;
    try {
      this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    } catch (err) {
      this.renderer = null;
      element.dataset.state = "no-webgl";
      const message = document.createElement("p");
      message.className = "message";
      message.textContent = `This browser cannot draw the 3D view (WebGL: ${err.message}); the answers still work.`;
      element.appendChild(message);
      return;
    }
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    element.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x10161d);
    this.camera = new THREE.PerspectiveCamera(55, 1, 0.01, 200);
    this.camera.up.set(0, 0, 1);  // maps are z-up (world frame, metres)
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    new ResizeObserver(() => this.resize()).observe(element);
    this.resize();
  }

  resize() {
    if (!this.renderer) return;
    const width = Math.max(1, this.element.clientWidth), height = Math.max(1, this.element.clientHeight);
    this.renderer.setSize(width, height);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    if (this.renderer) this.renderer.render(this.scene, this.camera);
  }

  setMap(data) {
    this.element.dataset.points = String(data.count);
    if (!this.renderer) return;
    const positions = new Float32Array(data.positions);
    this.keys = Int32Array.from(data.keys);
    this.baseColors = Float32Array.from(data.colors, (c) => c / 255);
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
    geometry.setAttribute("color", new THREE.BufferAttribute(this.baseColors.slice(), 3));
    geometry.computeBoundingBox();
    if (this.mapPoints) this.scene.remove(this.mapPoints);
    this.mapPoints = new THREE.Points(geometry, new THREE.PointsMaterial({ size: 0.03, vertexColors: true }));
    this.scene.add(this.mapPoints);
    const box = geometry.boundingBox;
    if (box && !box.isEmpty()) {
      const center = box.getCenter(new THREE.Vector3()), size = box.getSize(new THREE.Vector3());
      const radius = Math.max(size.x, size.y, size.z, 0.5);
      this.controls.target.copy(center);
      this.camera.position.set(center.x - 0.6 * radius, center.y - 0.9 * radius, center.z + 0.9 * radius);
      this.camera.far = radius * 20;
      this.camera.updateProjectionMatrix();
      this.controls.update();
    }
    this.element.dataset.state = "ready";
    this.render();
  }

  // Highlight one answer: its own points (from the query reply) in orange, its box, the rest of
  // the map dimmed; data-highlight-key / -count say what is highlighted.
  showAnswer(region) {
    if (this.highlight) {
      this.scene.remove(this.highlight);
      this.highlight = null;
    }
    if (!region) {
      this.element.dataset.highlightKey = "";
      this.element.dataset.highlightCount = "0";
      this.recolor(null);
      this.render();
      return;
    }
    const count = Math.floor(region.points.length / 3);
    this.element.dataset.highlightKey = String(region.key);
    this.element.dataset.highlightCount = String(count);
    if (!this.renderer) return;
    this.recolor(region.key);
    const group = new THREE.Group();
    if (count > 0) {
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(new Float32Array(region.points), 3));
      group.add(new THREE.Points(geometry, new THREE.PointsMaterial({ size: 0.045, color: 0xff8c1a })));
    }
    const lo = new THREE.Vector3(...region.bbox_min), hi = new THREE.Vector3(...region.bbox_max);
    const box = new THREE.Box3(lo, hi);
    group.add(new THREE.Box3Helper(box, 0xffd21f));
    this.highlight = group;
    this.scene.add(group);
    this.render();
  }

  recolor(key) {
    if (!this.mapPoints) return;
    const colors = this.mapPoints.geometry.getAttribute("color");
    for (let i = 0; i < this.keys.length; i++) {
      const dim = key === null ? 1.0 : (this.keys[i] === key ? 1.0 : 0.45);
      colors.array[3 * i] = this.baseColors[3 * i] * dim;
      colors.array[3 * i + 1] = this.baseColors[3 * i + 1] * dim;
      colors.array[3 * i + 2] = this.baseColors[3 * i + 2] * dim;
    }
    colors.needsUpdate = true;
  }
}

// ------------------------------------------------------------------------------ answers

let view = null;
let answers = [];

function cell(row, text, className) {
  const td = document.createElement("td");
  td.textContent = text;
  if (className) td.className = className;
  row.appendChild(td);
}

// Forget the answers on screen (a failed query must not leave the previous query's answers under
// its error line).
function clearAnswers() {
  answers = [];
  $("answer-rows").replaceChildren();
  $("answers").hidden = true;
  $("query-echo").hidden = true;
  $("query-shown").textContent = "";
  $("query-space").textContent = "";
  if (view) view.showAnswer(null);
}

function showAnswers(reply) {
  answers = Array.isArray(reply.regions) ? reply.regions : [];
  $("query-shown").textContent = reply.query;
  $("query-space").textContent = `(${reply.embedding_space})`;
  $("query-echo").hidden = false;
  const table = $("answers"), rows = $("answer-rows");
  rows.replaceChildren();
  table.classList.toggle("has-relevancy", answers.some((a) => a.relevancy !== undefined));
  table.classList.toggle("has-match", answers.some((a) => a.match !== undefined));
  answers.forEach((answer, i) => {
    const row = document.createElement("tr");
    row.dataset.key = String(answer.key);
    row.dataset.rank = String(i + 1);
    cell(row, String(i + 1));
    cell(row, answer.label === null || answer.label === undefined ? `region ${answer.key}` : String(answer.label), "label");
    cell(row, fixed(answer.score, 3), "score");
    cell(row, shown(answer.relevancy), "opt relevancy");
    row.lastChild.dataset.field = "relevancy";
    cell(row, shown(answer.match), "opt match");
    row.lastChild.dataset.field = "match";
    cell(row, String(answer.num_points), "points");
    const lo = answer.bbox_min.map((v) => fixed(v, 2)).join(", "), hi = answer.bbox_max.map((v) => fixed(v, 2)).join(", ");
    cell(row, `[${lo}] ..\n[${hi}]`, "box");  // two lines: the table fits the panel
    row.addEventListener("click", () => select(i));
    rows.appendChild(row);
  });
  table.hidden = answers.length === 0;
  setStatus(answers.length ? `${answers.length} answers, best first` : "No region answers this query.");
  select(answers.length ? 0 : -1);
}

function select(index) {
  for (const row of $("answer-rows").children) {
    const chosen = Number(row.dataset.rank) === index + 1;
    row.classList.toggle("selected", chosen);
    row.setAttribute("aria-selected", chosen ? "true" : "false");
  }
  if (view) view.showAnswer(index >= 0 ? answers[index] : null);
}

async function ask(event) {
  event.preventDefault();
  const text = $("query-text").value;
  if (!text.trim()) {
    setStatus("Type what to look for first.", true);
    return;
  }
  setStatus("Asking…");
  $("query-button").disabled = true;
  try {
    showAnswers(await getJson(`/api/query?text=${encodeURIComponent(text)}&top_k=${TOP_K}`));
  } catch (err) {
    clearAnswers();
    setStatus(err.message, true);
  } finally {
    $("query-button").disabled = false;
  }
}

// ------------------------------------------------------------------------------- health

// A live service's badge: its rate and errors, or "no stats yet" until it has published them
// (never an empty figure such as "– fps").
function statsText(s) {
  if (typeof s.fps !== "number" || !Number.isFinite(s.fps)) return "no stats yet";
  const errors = typeof s.errors === "number" && s.errors > 0 ? `, ${s.errors} errors` : "";
  return `${fixed(s.fps, 1)} fps${errors}`;
}

async function refreshHealth() {
  const list = $("health");
  try {
    const data = await getJson("/api/health");
    const items = [];
    const seen = new Set();
    for (const s of data.services) {
      seen.add(s.service);
      const li = document.createElement("li");
      li.className = s.alive ? "alive" : "down";
      li.dataset.service = s.service;
      li.textContent = s.alive ? `${s.service} ${statsText(s)}` : `${s.service} down`;
      items.push(li);
    }
    for (const name of NEEDED_SERVICES.filter((n) => !seen.has(n))) {
      const li = document.createElement("li");
      li.className = "down";
      li.dataset.service = name;
      li.textContent = `${name} down`;
      items.push(li);
    }
    list.replaceChildren(...items);
  } catch (err) {
    const li = document.createElement("li");
    li.className = "down";
    li.textContent = `health unknown: ${err.message}`;
    list.replaceChildren(li);
  }
}

async function main() {
  view = new MapView($("viewer"));
  $("query-form").addEventListener("submit", ask);
  try {
    const info = await getJson("/api/info");
    $("map-id").textContent = info.map_id;
    document.title = `${info.map_id} · OpenFusion-Z query page`;
    $("query-text").maxLength = info.max_text_chars;
  } catch (err) {
    setStatus(err.message, true);
  }
  refreshHealth();
  setInterval(refreshHealth, HEALTH_PERIOD_MS);
  try {
    const points = await getJson("/api/points");
    view.setMap(points);
    setStatus(`Map of ${points.count} surface points${points.truncated ? " (subsampled)" : ""}. Ask away.`);
  } catch (err) {
    view.element.dataset.state = "no-map";
    setStatus(`No map points: ${err.message}`, true);
  }
  document.body.dataset.ready = "true";
}

main();
