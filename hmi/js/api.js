// HTTP helpers. Every answer of the supervisor is JSON; a 401 means no (or an expired)
// session: the page goes to the login screen and comes back to the same place after.

import { t } from "./i18n.js";

const listeners = { unauthorized: [] };

/** Call fn() whenever a request answers 401 (app.js sends the page to the login). */
export function onUnauthorized(fn) {
  listeners.unauthorized.push(fn);
}

/**
 * Request `path` with an optional JSON `body`. Resolves to {ok, status, data}; never
 * throws for an HTTP error (a refusal is data: its reason is shown to the operator).
 */
export async function api(method, path, body, opts = {}) {
  const init = { method, headers: {}, credentials: "same-origin" };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  let res;
  try {
    res = await fetch(path, init);
  } catch (err) {
    return { ok: false, status: 0, data: { reason: t("api.unreachable", { error: err.message }) } };
  }
  let data = null;
  const text = await res.text();
  try {
    data = text ? JSON.parse(text) : {};
  } catch {
    data = { reason: text.slice(0, 300) || res.statusText };
  }
  if (res.status === 401 && !opts.no401) {
    for (const fn of listeners.unauthorized) fn();
  }
  return { ok: res.ok, status: res.status, data };
}

export const get = (path, opts) => api("GET", path, undefined, opts);
export const post = (path, body, opts) => api("POST", path, body ?? {}, opts);
export const put = (path, body, opts) => api("PUT", path, body, opts);

/** The reason of a refused answer, as one line for the operator. */
export function reasonOf(answer) {
  const d = answer.data || {};
  let reason = d.reason || d.error || d.message || `HTTP ${answer.status}`;
  if (Array.isArray(d.details) && d.details.length) reason += ": " + d.details.join("; ");
  return reason;
}
