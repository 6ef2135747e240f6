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

async function request(method, path, body, { isForm = false, anonymous = false } = {}) {
  const init = { method, headers: {} };
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
  logout: () => request("POST", "/auth/logout"),
};

// EventSource tells nothing of why a stream failed (a 401 looks like a
// dropped connection), so a failing stream asks GET /auth/me, one at a time:
// a 401 there raises UNAUTHORIZED as any API call does.
let checkingLogin = null;
function checkLogin() {
  checkingLogin ??= request("GET", "/auth/me").catch(() => null).finally(() => { checkingLogin = null; });
}

// A server-sent event stream with named events; `handlers` maps an event name
// to a function of its parsed data. EventSource reconnects by itself; the
// service then sends a fresh snapshot. Returns a function that closes it.
export function stream(path, handlers, onState) {
  const source = new EventSource(path);
  for (const [name, handler] of Object.entries(handlers)) {
    source.addEventListener(name, (event) => handler(JSON.parse(event.data)));
  }
  source.onopen = () => onState && onState("open");
  source.onerror = () => {
    if (onState) onState(source.readyState === EventSource.CLOSED ? "closed" : "reconnecting");
    checkLogin();
  };
  return () => source.close();
}
