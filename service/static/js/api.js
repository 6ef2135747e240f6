// The HTTP API, as the dashboard uses it: JSON in and out, errors as ApiError.

export class ApiError extends Error {
  // status: HTTP status; detail: FastAPI's `detail` (a string, or a list of
  // {loc, msg, type} for 422s); fields: {field: message} from that list.
  constructor(status, detail) {
    super(ApiError.describe(status, detail));
    this.status = status;
    this.detail = detail;
    this.fields = {};
    if (Array.isArray(detail)) {
      for (const item of detail) {
        const loc = (item.loc || []).filter((part) => part !== "body" && part !== "query");
        const field = loc.length ? String(loc[0]) : "_";
        const key = field === "options" && loc.length > 1 ? `options.${loc[1]}` : field;
        this.fields[key] = this.fields[key] ? `${this.fields[key]}\n${item.msg}` : item.msg;
      }
    }
  }

  static describe(status, detail) {
    if (Array.isArray(detail)) return detail.map((d) => d.msg).join("; ");
    if (typeof detail === "string") return detail;
    return `HTTP ${status}`;
  }
}

// The dashboard logs in with a session cookie; a request that changes
// something echoes the CSRF cookie in a header (the service's double-submit check).
function csrfToken() {
  const match = /(?:^|;\s*)rayfarm_csrf=([^;]*)/.exec(document.cookie);
  return match ? decodeURIComponent(match[1]) : "";
}

// The session cookie is HttpOnly (no script reads it); the CSRF cookie comes
// and goes with it, so its absence means this browser is not logged in.
export function hasLoginCookie() {
  return csrfToken() !== "";
}

// Any 401 means this browser's login is gone (logged out in another tab,
// expired, revoked): the API says so with this window event, and main.js
// shows the login page. `anonymous` requests (logging in, asking who we are)
// handle their 401 themselves.
export const UNAUTHORIZED = "rayfarm:unauthorized";

async function request(method, path, body, { isForm = false, anonymous = false, token = null } = {}) {
  const init = { method, headers: {} };
  if (token !== null) init.headers.authorization = `Bearer ${token}`;
  if (method !== "GET") init.headers["x-csrf-token"] = csrfToken();
  if (body !== undefined) {
    if (isForm) init.body = body;
    else {
      init.body = JSON.stringify(body);
      init.headers["content-type"] = "application/json";
    }
  }
  let response;
  try {
    response = await fetch(path, init);
  } catch (err) {
    throw new ApiError(0, `the service does not answer (${err.message})`);
  }
  if (response.status === 401 && !anonymous) window.dispatchEvent(new CustomEvent(UNAUTHORIZED));
  if (response.status === 204) return null;
  const text = await response.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = text; }
  if (!response.ok) throw new ApiError(response.status, data && data.detail !== undefined ? data.detail : data);
  return data;
}

export const api = {
  get: (path) => request("GET", path),
  post: (path, body) => request("POST", path, body),
  patch: (path, body) => request("PATCH", path, body),
  del: (path) => request("DELETE", path),
  upload: (path, form) => request("POST", path, form, { isForm: true }),
  // The session (service/api/routes/auth.py): POST /auth/login answers 401 for
  // a bad token, which is the login form's business, not a lost login.
  me: () => request("GET", "/auth/me", undefined, { anonymous: true }),
  login: (token) => request("POST", "/auth/login", { token }, { anonymous: true }),
  // Whose token this is, without logging in with it (a login link's, before asking).
  whoIs: (token) => request("GET", "/auth/me", undefined, { anonymous: true, token }),
  logout: () => request("POST", "/auth/logout"),
};

// EventSource tells nothing of why a stream failed (a 401 looks like a
// dropped connection), so a failing stream asks GET /auth/me, one at a time:
// a 401 there raises UNAUTHORIZED as any API call does.
let checkingLogin = null;
function checkLogin() {
  checkingLogin ??= request("GET", "/auth/me").catch(() => null).finally(() => { checkingLogin = null; });
}

// -- the connection ----------------------------------------------------------------
// The pages live on event streams (and the top bar on /healthz). While any of
// them is broken, a banner under the top bar says so, with the time the data
// on the page was last known to be current, until they are all back.
const broken = new Set(); // the links (streams, the health poll) down now
let goodUntil = null; // when the first of them broke

export function connectionState(link, ok) {
  const before = broken.size;
  if (ok) broken.delete(link);
  else if (!broken.has(link)) {
    if (!before) goodUntil = new Date();
    broken.add(link);
  }
  if (before === broken.size) return;
  document.body.classList.toggle("offline", broken.size > 0);
  let banner = document.getElementById("connection-lost");
  if (!broken.size) {
    if (banner) banner.hidden = true;
    return;
  }
  if (!banner) {
    banner = document.createElement("div");
    banner.id = "connection-lost";
    banner.className = "conn-banner";
    banner.setAttribute("role", "alert");
    document.body.insertBefore(banner, document.getElementById("view"));
  }
  const at = goodUntil.toLocaleTimeString("en-GB", { hour12: false });
  banner.textContent = `Connection lost — data as of ${at}. Reconnecting…`;
  banner.dataset.asOf = goodUntil.toISOString();
  banner.hidden = false;
}

export function offline() {
  return broken.size > 0;
}

// A server-sent event stream with named events; `handlers` maps an event name
// to a function of its parsed data. EventSource reconnects by itself after a
// dropped connection, and the service then sends a fresh snapshot; after an
// HTTP error it gives up (CLOSED), so this opens a new one a few seconds
// later. Either way the connection banner shows meanwhile. Returns a function
// that closes it.
const REOPEN_MS = 3000;
export function stream(path, handlers, onState) {
  const link = {};
  let source = null;
  let timer = null;
  let closed = false;
  function open() {
    source = new EventSource(path);
    for (const [name, handler] of Object.entries(handlers)) {
      source.addEventListener(name, (event) => handler(JSON.parse(event.data)));
    }
    source.onopen = () => {
      connectionState(link, true);
      if (onState) onState("open");
    };
    source.onerror = () => {
      if (closed) return;
      connectionState(link, false);
      const gone = source.readyState === EventSource.CLOSED;
      if (onState) onState(gone ? "closed" : "reconnecting");
      checkLogin();
      if (gone) {
        source.close();
        timer = setTimeout(() => { if (!closed) open(); }, REOPEN_MS);
      }
    };
  }
  open();
  return () => {
    closed = true;
    clearTimeout(timer);
    source.close();
    connectionState(link, true);
  };
}
