// The login page: paste a token, trade it for this browser's session cookie
// (POST /auth/login), go on to where the user was going.
//   #/login                    plain
//   #/login?next=#/jobs/<id>   sent here by a 401; goes on there afterwards
//   #/login?failed=1           the login link's token was refused (GET /?token=)
//   #/login?ended=1            the login ended (logged out elsewhere, expired, revoked)
//   #/login?link=1             a login link the service would not use by itself: asks first

import { api } from "../api.js";
import { session, setMe } from "../session.js";
import { h, replace } from "../ui.js";

// Only a route of this dashboard, and never the login page itself.
export function safeNext(next) {
  return typeof next === "string" && next.startsWith("#/") && !next.startsWith("#/login") ? next : "#/jobs";
}

// People paste the whole login URL as often as the token: take the token out of it.
export function tokenOf(text) {
  const value = text.trim();
  const match = /[?&]token=([^&#\s]+)/.exec(value);
  return match ? decodeURIComponent(match[1]) : value;
}

// The token of a login link that came from another site (main.js holds it
// here, out of the address bar). Using it needs the user's yes: it could be
// someone else's token, and this browser would then work in their account.
let heldLink = null;

export function holdLoginLink(token) {
  heldLink = token;
}

export function loginView(root, params) {
  if (params.get("link") === "1" && heldLink !== null) {
    linkView(root, heldLink, safeNext(params.get("next")));
    return;
  }
  const next = safeNext(params.get("next"));
  const token = h("input#login-token", { type: "password", name: "token", autocomplete: "off",
    spellcheck: "false", placeholder: "rf_…", "aria-describedby": "login-help", required: true });
  const button = h("button.primary#login-button", { type: "submit" }, "Log in");
  const error = h("div#login-error", { role: "alert" });
  if (params.get("failed") === "1") {
    replace(error, h("div.error-box#login-failed", {}, "The login link's token was not accepted: it is "
      + "unknown, expired or revoked. Paste a valid token below, or ask an admin for a new one."));
  } else if (params.get("ended") === "1") {
    replace(error, h("div.notice#login-ended", {}, "Your login has ended (logged out, expired or revoked). "
      + "Log in again to go on."));
  }
  const already = session.me ? h("div.notice#login-already", {}, "You are logged in as ",
    h("b", {}, session.me.user), ` (${session.me.role}). `, h("a", { href: next }, "Go on"),
    ", or log in with another token below.") : null;

  const form = h("form.panel.login#login-form", { novalidate: true },
    h("h1", {}, "Log in to rayfarm"),
    h("div.panel-body", {},
      already,
      error,
      h("div.field", {},
        h("label", { for: "login-token" }, "Token"),
        token,
        h("span.hint", {}, "An API token, or the whole login link: it is traded for a session cookie "
          + "of this browser, and not kept.")),
      h("div.actions", {}, button),
      h("div.login-help#login-help", {},
        h("h2", {}, "Where a token comes from"),
        h("ul", {},
          h("li", {}, "The admin's login link: ", h("code", {}, "rayfarm serve"),
            " prints it when it starts, ", h("code", {}, "http://HOST:PORT/?token=…"),
            ". Opening it logs you in at once; the token is also in the service's data directory, in ",
            h("code", {}, "admin.token"), "."),
          h("li", {}, "A token of your own: an admin runs ", h("code", {}, "rayfarm tokens create USER"),
            " on the service's machine (or calls ", h("code", {}, "POST /tokens"),
            ") and hands it to you. It is shown once."),
          h("li", {}, "Roles: an ", h("b", {}, "admin"), " sees and changes everything; an ",
            h("b", {}, "artist"), " submits and manages its own jobs; a ", h("b", {}, "viewer"),
            " sees every job and changes none.")))));
  replace(root, form);
  token.focus();

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const secret = tokenOf(token.value);
    if (!secret) {
      replace(error, h("div.error-box", {}, "Paste a token first."));
      token.focus();
      return;
    }
    button.disabled = true;
    try {
      setMe(await api.login(secret));
      token.value = "";
      location.hash = next;
    } catch (err) {
      replace(error, h("div.error-box#login-refused", {}, err.status === 401
        ? "This token was not accepted: it is unknown, expired or revoked, or its user is disabled."
        : `Could not log in: ${err.message}`));
      token.select();
    } finally {
      button.disabled = false;
    }
  });
}

// Asks before a login link from elsewhere is used, naming whose it is.
function linkView(root, token, next) {
  const who = h("p#link-user", {}, "Asking the service whose link this is…");
  const error = h("div#login-error", { role: "alert" });
  const confirm = h("button.primary#link-login", { type: "submit", disabled: true }, "Log in");
  const cancel = h("button#link-cancel", { type: "button" }, "Cancel");
  const already = session.me ? h("div.notice#login-already", {}, "You are logged in as ",
    h("b", {}, session.me.user), ` (${session.me.role}). Cancel to stay so.`) : null;
  const form = h("form.panel.login#link-form", { novalidate: true },
    h("h1", {}, "Log in with this link?"),
    h("div.panel-body", {},
      h("div.notice#link-why", {}, "This login link was opened from another site, or the browser "
        + "did not say from where, so it was not used by itself. Use it only if it is yours: a link "
        + "from someone else logs this browser into their account, and what you upload goes there."),
      already,
      who,
      error,
      h("div.actions", {}, confirm, cancel)));
  replace(root, form);

  const forget = () => { heldLink = null; };
  api.whoIs(token).then((me) => {
    replace(who, "It logs this browser in as ", h("b#link-user-name", {}, me.user), ` (${me.role}).`);
    confirm.textContent = `Log in as ${me.user}`;
    confirm.disabled = false;
    confirm.focus();
  }, (err) => {
    forget();
    who.remove();
    confirm.remove();
    replace(error, h("div.error-box#login-failed", {}, err.status === 401
      ? "The login link's token was not accepted: it is unknown, expired or revoked."
      : `Could not check the login link: ${err.message}`));
  });
  cancel.addEventListener("click", () => {
    forget();
    location.replace(session.me ? next : "#/login");
  });
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    confirm.disabled = true;
    try {
      setMe(await api.login(token));
      forget();
      location.hash = next;
    } catch (err) {
      replace(error, h("div.error-box#login-refused", {}, `Could not log in: ${err.message}`));
      confirm.disabled = false;
    }
  });
}
