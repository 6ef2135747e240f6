// Who is logged in (GET /auth/me) and what that user's role lets the dashboard
// offer. The service decides (service/access.py); this only hides or disables
// what it would refuse, and says why.
//
//   await refresh();            // session.me: {user, role, via, token_id} or null
//   may.submit()                // admins and artists
//   may.change(job)             // admins, and artists on their own jobs
//   readOnlyReason()            // why a viewer's buttons are off, or ""

import { api, hasLoginCookie } from "./api.js";

export const session = { me: null };

const listeners = new Set();

export function onSessionChange(listener) {
  listeners.add(listener);
}

export function setMe(me) {
  session.me = me ? { user: me.user, role: me.role, via: me.via, token_id: me.token_id } : null;
  for (const listener of listeners) listener(session.me);
}

// Ask the service who this browser is logged in as. Without the CSRF cookie
// there is no login to ask about (and no 401 to provoke).
export async function refresh() {
  if (!hasLoginCookie()) {
    setMe(null);
    return null;
  }
  try {
    setMe(await api.me());
  } catch (err) {
    if (err.status !== 401) throw err;
    setMe(null);
  }
  return session.me;
}

export const may = {
  submit: () => !!session.me && (session.me.role === "admin" || session.me.role === "artist"),
  change: (job) => !!session.me && (session.me.role === "admin"
    || (session.me.role === "artist" && (!job || job.owner === session.me.user))),
};

export function readOnlyReason() {
  if (!session.me || session.me.role !== "viewer") return "";
  return `${session.me.user} is a viewer: viewers see every job and change none`;
}
