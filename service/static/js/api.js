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

async function request(method, path, body, isForm = false) {
  const init = { method, headers: {} };
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
  upload: (path, form) => request("POST", path, form, true),
};

// A server-sent event stream with named events; `handlers` maps an event name
// to a function of its parsed data. EventSource reconnects by itself; the
// service then sends a fresh snapshot. Returns a function that closes it.
export function stream(path, handlers, onState) {
  const source = new EventSource(path);
  for (const [name, handler] of Object.entries(handlers)) {
    source.addEventListener(name, (event) => handler(JSON.parse(event.data)));
  }
  source.onopen = () => onState && onState("open");
  source.onerror = () => onState && onState(source.readyState === EventSource.CLOSED ? "closed" : "reconnecting");
  return () => source.close();
}
