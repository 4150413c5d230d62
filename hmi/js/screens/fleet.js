// The fleet: one tile per bench of the Sparkplug group (GET /api/fleet, supervisor/fleet/),
// each with its channels' state, step, V, I and progress, its active alarms when the bench
// publishes them, and a link to its own screens when it publishes their address.
// High-performance HMI: grey when normal; an offline bench is the abnormal one (its
// channels' last known values stay, greyed, under "last known values").
import { esc } from "../dom.js";
import { fmtDateTime, fmtNumber, t, tValue } from "../i18n.js";

const dash = "—";
const num = (v, digits) => (typeof v === "number" ? fmtNumber(v, digits) : dash);

function channelRow(c) {
  const pct = typeof c.progress === "number" ? `${fmtNumber(c.progress * 100, 0)} %` : dash;
  return `<tr data-channel="${esc(c.id)}">
    <th scope="row" translate="no">${esc(c.id)}</th>
    <td>${esc(tValue("chain", c.state) ?? dash)}</td>
    <td>${esc(c.step || dash)}</td>
    <td class="num">${esc(num(c.voltage_v, 3))}</td>
    <td class="num">${esc(num(c.current_a, 3))}</td>
    <td class="num">${esc(pct)}</td>
  </tr>`;
}

function benchTile(n) {
  // (a bench heard of only by its data waits for the births the fleet asked: not a fault)
  let status = t("fleet.offline");
  let cls = " abn";
  if (n.online) [status, cls] = n.in_sync ? [t("fleet.online"), ""] : [t("fleet.resync"), " warn"];
  else if (!n.born) [status, cls] = [t("fleet.unborn"), " warn"];
  const name = n.url
    ? `<a href="${esc(n.url)}" translate="no" title="${esc(t("fleet.openBench"))}">${esc(n.id)}</a>`
    : `<span class="tile-name" translate="no">${esc(n.id)}</span>`;
  const alarms =
    typeof n.alarms_active === "number"
      ? `<div class="${n.alarms_active > 0 ? "abn" : ""}">${esc(t("fleet.alarms", { count: n.alarms_active, n: n.alarms_active }))}</div>`
      : "";
  const head = `<tr><th scope="col">${esc(t("fleet.col.channel"))}</th><th scope="col">${esc(t("fleet.col.state"))}</th>
    <th scope="col">${esc(t("fleet.col.step"))}</th><th scope="col" class="num">${esc(t("fleet.col.voltage"))}</th>
    <th scope="col" class="num">${esc(t("fleet.col.current"))}</th><th scope="col" class="num">${esc(t("fleet.col.progress"))}</th></tr>`;
  const channels = n.channels.length
    ? `<table class="fleet-channels${n.online ? "" : " last-known"}"><caption class="${n.online ? "sr-only" : "muted"}">${esc(n.online ? t("fleet.channelsOf", { bench: n.id }) : t("fleet.lastKnown"))}</caption>
        <thead>${head}</thead><tbody>${n.channels.map(channelRow).join("")}</tbody></table>`
    : `<p class="muted">${esc(t("fleet.noChannels"))}</p>`;
  return `<section class="tile bench-tile${cls}" id="bench-${esc(n.id)}" data-bench="${esc(n.id)}" data-online="${n.online}" aria-label="${esc(n.id)}">
    <div class="tile-head">${name}<span class="status">${esc(status)}</span>
      <span class="since">${esc(t("fleet.since", { at: fmtDateTime(n.since_ms / 1000) }))}</span></div>
    ${alarms}${channels}
  </section>`;
}

/** Paint the fleet's answer into `root` (and the header's counts). */
export function paint(root, data) {
  const counts = document.getElementById("fleet-counts");
  if (counts) counts.textContent = t("fleet.counts", { online: data.online, offline: data.offline });
  const group = document.getElementById("fleet-group");
  if (group) group.textContent = data.group;
  const link = document.getElementById("link");
  if (link) {
    link.textContent = data.broker_connected ? t("fleet.brokerOk") : t("fleet.brokerLost");
    link.classList.toggle("abn", !data.broker_connected);
  }
  root.innerHTML = data.nodes.length
    ? `<h1 class="sr-only">${esc(t("fleet.title"))}</h1><div class="tiles fleet-tiles">${data.nodes.map(benchTile).join("")}</div>`
    : `<h1>${esc(t("fleet.title"))}</h1><p class="fleet-empty muted">${esc(t("fleet.none"))}</p>`;
}
