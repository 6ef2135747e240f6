// Small DOM and formatting helpers shared by the views.

// h("div.cls#id", {attr: v, onclick: f}, ...children): an element.
export function h(spec, attrs = {}, ...children) {
  const [, tag = "div", rest = ""] = /^([a-z0-9]*)(.*)$/i.exec(spec);
  const el = document.createElement(tag || "div");
  for (const part of rest.match(/[.#][^.#]+/g) || []) {
    if (part[0] === ".") el.classList.add(part.slice(1));
    else el.id = part.slice(1);
  }
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === undefined || value === null || value === false) continue;
    if (key.startsWith("on")) el.addEventListener(key.slice(2), value);
    else if (key === "dataset") Object.assign(el.dataset, value);
    else if (key === "style" && typeof value === "object") Object.assign(el.style, value);
    else if (value === true) el.setAttribute(key, "");
    else el.setAttribute(key, value);
  }
  append(el, children);
  return el;
}

function append(el, children) {
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    el.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
}

export function replace(el, ...children) {
  el.replaceChildren();
  append(el, children);
  return el;
}

export const fmt = {
  count(n) {
    if (n === null || n === undefined) return "–";
    const units = [[1e12, "T"], [1e9, "G"], [1e6, "M"], [1e3, "k"]];
    for (const [size, suffix] of units) {
      if (Math.abs(n) >= size) return `${(n / size).toFixed(n / size >= 100 ? 0 : 1)}${suffix}`;
    }
    return String(Math.round(n));
  },
  rate(n) { return n ? `${fmt.count(n)}/s` : "–"; },
  duration(seconds) {
    if (seconds === null || seconds === undefined || !isFinite(seconds)) return "–";
    if (seconds < 10) return `${seconds.toFixed(1)} s`;
    const s = Math.round(seconds);
    if (s < 60) return `${s} s`;
    const m = Math.floor(s / 60);
    if (m < 60) return `${m}m ${String(s % 60).padStart(2, "0")}s`;
    const hours = Math.floor(m / 60);
    if (hours < 48) return `${hours}h ${String(m % 60).padStart(2, "0")}m`;
    return `${Math.floor(hours / 24)}d ${hours % 24}h`;
  },
  ago(iso) {
    if (!iso) return "–";
    const seconds = (Date.now() - Date.parse(iso)) / 1000;
    if (seconds < 5) return "just now";
    return `${fmt.duration(seconds)} ago`;
  },
  time(iso) {
    if (!iso) return "–";
    const d = new Date(iso);
    const sameDay = d.toDateString() === new Date().toDateString();
    return sameDay ? d.toLocaleTimeString() : d.toLocaleString();
  },
  percent(f) { return `${(100 * (f || 0)).toFixed(f >= 0.995 || f === 0 ? 0 : 1)}%`; },
};

export function badge(state) {
  return h(`span.badge.st-${state}`, { "data-state": state }, state);
}

export function progressBar(fraction, label, status = "", big = false) {
  const bar = h(`div.progress${big ? ".big" : ""}`, { role: "progressbar", "aria-valuemin": 0,
    "aria-valuemax": 100, "aria-valuenow": Math.round(100 * (fraction || 0)) });
  if (status) bar.classList.add(status);
  bar.append(h("div.fill", { style: { width: `${100 * Math.min(Math.max(fraction || 0, 0), 1)}%` } }),
    h("span.label", {}, label));
  return bar;
}

export function toast(message, bad = false) {
  const el = h(`div.toast${bad ? ".bad" : ""}`, {}, message);
  document.getElementById("toasts").append(el);
  setTimeout(() => el.remove(), bad ? 8000 : 4000);
}

// What a job's status allows (mirrors service/states.py and service/jobs.py).
export const FINAL = new Set(["done", "failed", "canceled"]);
