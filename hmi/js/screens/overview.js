// Overview: the bench mimic (e-stop, supply, contactor, BMS) and one tile per channel.
// Every tag it shows is named by /api/bench (supervisor/hmi/layout.py): no device names here.
// High-performance HMI: grey when normal; colour only for what is abnormal.
import { post } from "../api.js";
import { alarmText, bindTags, esc, fmtDuration, showResult, $, $$ } from "../dom.js";
import { fmtNumber, t, tValue } from "../i18n.js";
import { priorityIcon } from "../priority.js";

const tr = t; // (channelTile's own `t` is the channel's tags)
const onOff = () => `data-true="${esc(t("value.on"))}" data-false="${esc(t("value.off"))}"`;
/** A device line's label from /api/bench ("voltage", "link"...) in the language, where the
 * catalogue has it (mimic.row.LABEL), else as the supervisor names it. */
const tOrLabel = (label) => tValue("mimic.row", label);

/** The tag of a mimic element: /api/bench gives a tag name or {tag: name, ...}. */
const mimicTag = (m) => (m && typeof m === "object" ? m.tag : m) || null;

function mimicBox(id, title, rows) {
  return `<section class="mimic-box" id="mimic-${id}" aria-label="${esc(title)}">
    <h3>${esc(title)}</h3>${rows.join("")}</section>`;
}

const row = (label, tag, attrs = "") =>
  tag
    ? `<div class="kv"><span>${esc(label)}</span><b data-tag="${esc(tag)}" ${attrs}></b></div>`
    : "";

/** What the channel does, from its state (chN.state), commanded current and mode:
 * "charging 20.000 A, manual", "idle, auto" (supervisor/channels/activity.py writes the
 * same for `supervisor ctl status`). The step chain's state is shown beside it, never
 * in its place: a channel driven in Manual is charging while its chain is Idle. */
export function activityLabel(state, currentCmd, mode) {
  let text = state === null || state === undefined || state === "" ? "—" : tValue("chState", String(state));
  if ((state === "charging" || state === "discharging") && typeof currentCmd === "number")
    text += ` ${fmtNumber(Math.abs(currentCmd), 3)} A`;
  if (mode !== null && mode !== undefined && mode !== "") text += `, ${tValue("mode", mode)}`;
  return text;
}

export function channelTile(ch) {
  const t = ch.tags;
  return `<a class="tile" href="#/channel/${esc(ch.name)}" id="tile-${esc(ch.name)}" data-channel="${esc(ch.name)}">
    <div class="tile-head"><span class="tile-name">${esc(ch.name)}</span>
      <span class="activity"></span>
      <span class="chain-state">${esc(tr("tile.chain"))} <span class="state" data-tag="${esc(t.state)}" data-enum="chain"></span></span></div>
    <div class="tile-desc muted">${esc(ch.description || "")}</div>
    <div class="step">${esc(tr("tile.step"))} <span data-tag="${esc(t.step)}" data-empty="${esc(tr("value.none"))}"></span></div>
    <div class="nums">
      <div><span class="big" data-tag="${esc(t.voltage)}" data-fmt="n3"></span><small>${esc(tr("quantity.voltage"))}</small></div>
      <div><span class="big" data-tag="${esc(t.current)}" data-fmt="n3"></span><small>${esc(tr("quantity.current"))}</small></div>
      <div><span class="big" data-tag="${esc(t.temperature)}" data-fmt="n1"></span><small>${esc(tr("quantity.temperature"))}</small></div>
      <div><span class="big" data-tag="${esc(t.charge)}" data-fmt="n4"></span><small>${esc(tr("quantity.charge"))}</small></div>
    </div>
    <div class="progress"><div class="bar" role="progressbar" aria-label="${esc(tr("tile.progressOf", { ch: ch.name }))}" aria-valuemin="0" aria-valuemax="100"><div class="fill"></div></div>
      <span class="eta">${esc(tr("tile.eta"))} <span class="eta-text">—</span></span></div>
    <div class="tile-alarm" aria-live="polite"></div>
  </a>`;
}

/** The chain states in which a test is under way and its ETA counts down. */
const RUNNING = /^(Running|Resuming)$/;

/** Repaint what is not a single tag: what the channel does, the progress bar, ETA and
 * the alarm colour. */
export function paintTile(el, ch, live) {
  const t = ch.tags;
  $(".activity", el).textContent = activityLabel(
    live.value(t.channel_state),
    live.value(t.current_cmd),
    live.value(t.mode),
  );
  const progress = Number(live.value(t.progress)) || 0;
  const pct = Math.max(0, Math.min(100, progress * 100));
  const bar = $(".bar", el);
  $(".fill", el).style.width = `${pct}%`;
  bar.setAttribute("aria-valuenow", String(Math.round(pct)));
  const state = String(live.value(t.state) || "");
  // The time left means something only while the chain runs: the tag keeps its last
  // figure after an Abort, a Stop or a Hold (the chain stops updating it), which would
  // read as a test still under way.
  $(".eta-text", el).textContent = RUNNING.test(state) ? fmtDuration(live.value(t.eta)) : "—";
  const alarms = live.alarms.filter((a) => a.group === ch.name && a.state !== "normal" && !a.shelved);
  const fault = live.value(t.fault);
  const abnormal = alarms.length > 0 || (typeof fault === "string" && fault !== "");
  el.classList.toggle("abn", abnormal);
  el.classList.toggle("warn", !abnormal && /^(Held|Holding|Aborted|Stopped)$/.test(state));
  paintTileAlarm($(".tile-alarm", el), abnormal ? alarms : [], abnormal ? fault : "");
}

/** The tile's alarm line: its highest-priority alarm with the priority's shape (ISA-101:
 * not colour alone), else the channel's latched fault; rewritten only when it changes
 * (paintTile runs at every tag change). */
function paintTileAlarm(el, alarms, fault) {
  const top = alarms.slice().sort((x, y) => (y.severity || 0) - (x.severity || 0))[0];
  const html = top ? `${priorityIcon(top.severity)} ${esc(alarmText(top))}` : esc(fault || "");
  if (el.dataset.html === html) return;
  el.dataset.html = html;
  el.innerHTML = html;
}

const linkAttrs = () => `data-true="${esc(t("value.linkOk"))}" data-false="${esc(t("value.linkLost"))}" data-abn="false"`;

/** The lines of a device's mimic box, as /api/bench describes them (its kind's "shows":
 * label, tag, format): the screen knows no device name and no kind. */
function shownRows(device) {
  return (device?.shows || []).map((s) =>
    row(tOrLabel(s.label), s.tag, s.format === "link" ? linkAttrs() : `data-fmt="${esc(s.format)}"`),
  );
}

/** The bench-wide software e-stop (seed 002 §1.5): the one red button of the screens
 * (ISA-101: red is for what stops the bench or is abnormal), behind a confirmation;
 * "Reset e-stop" is an ordinary button: the server refuses it, with the reason, until the
 * e-stop alarm is acknowledged (Alarms screen) and while the button is pressed. */
function estopControls() {
  return `<div class="kv"><span>${esc(t("estop.trip"))}</span><b id="estop-trip">${esc(t("value.none"))}</b></div>
    <div class="estop-controls">
      <button type="button" class="estop" id="estop-press" aria-haspopup="dialog">${esc(t("estop.press"))}</button>
      <button type="button" class="small" id="estop-reset">${esc(t("estop.reset"))}</button>
    </div>`;
}

const estopDialog = () => `<dialog id="estop-confirm" aria-labelledby="estop-confirm-title">
    <h2 id="estop-confirm-title">${esc(t("estop.confirmTitle"))}</h2>
    <p>${esc(t("estop.confirmText1"))} <b>${esc(t("estop.reset"))}</b>${esc(t("estop.confirmText2"))}</p>
    <div class="buttons">
      <button type="button" class="estop" id="estop-confirm-yes">${esc(t("estop.press"))}</button>
      <button type="button" id="estop-confirm-no" autofocus>${esc(t("common.cancel"))}</button>
    </div>
  </dialog>`;

/** The bench's e-stop trip (the alarm ``estop``: the button or the software e-stop) as
 * the E-stop box shows it: "none", or its state and what pressed it, in the alarm colour. */
function paintEstopTrip(root, live) {
  const el = $("#estop-trip", root);
  if (!el) return;
  const a = live.alarms.find((x) => x.id === "estop" && x.state !== "normal");
  el.textContent = a ? `${tValue("alarmState", a.state)}: ${alarmText(a)}` : t("value.none");
  el.classList.toggle("abn", Boolean(a));
}

/** The e-stop buttons' handlers (on the Overview's root, whose HTML has them). */
function bindEstop(root) {
  const press = $("#estop-press", root);
  if (!press) return;
  const dialog = $("#estop-confirm", root);
  const out = $("#estop-result", root);
  press.addEventListener("click", () => dialog.showModal());
  $("#estop-confirm-no", root).addEventListener("click", () => dialog.close());
  $("#estop-confirm-yes", root).addEventListener("click", async () => {
    dialog.close();
    out.hidden = false;
    out.textContent = t("estop.pressing");
    showResult(out, await post("/api/estop"), t("estop.pressed"));
  });
  $("#estop-reset", root).addEventListener("click", async () => {
    out.hidden = false;
    out.textContent = t("estop.resetting");
    showResult(out, await post("/api/estop/reset"), t("estop.wasReset"));
  });
}

export async function render({ root, app }) {
  root.dataset.title = t("nav.overview");
  const b = app.bench;
  const m = b.mimic;
  const estop = mimicTag(m.estop);
  const supply = mimicTag(m.supply);
  const contactor = mimicTag(m.contactor);
  const bms = mimicTag(m.bms);
  const device = (name) => b.devices.find((d) => d.name === name);
  const mimic = [];
  if (estop)
    mimic.push(
      mimicBox("estop", t("mimic.estop"), [
        row(t("mimic.circuit"), estop, `data-true="${esc(t("value.closed"))}" data-false="${esc(t("value.pressed"))}" data-abn="false" class="big"`),
        estopControls(),
      ]),
    );
  if (supply)
    mimic.push(
      mimicBox("supply", t("mimic.supply"), [
        row(t("mimic.output"), supply, onOff()),
        ...shownRows(device(m.supply_device)),
      ]),
    );
  if (contactor)
    mimic.push(
      mimicBox("contactor", t("mimic.contactor"), [
        row(t("mimic.contacts"), contactor, `data-true="${esc(t("value.closed"))}" data-false="${esc(t("value.open"))}" class="big"`),
        row(t("mimic.coil"), mimicTag(m.coil), onOff()),
      ]),
    );
  if (bms) {
    // The BMS device's lines (its link first); without them (an older supervisor's answer)
    // the one tag the mimic names: its link, or on the oldest its pack voltage.
    const rows = shownRows(device(m.bms_device));
    const only = bms.endsWith(".connected") ? row(t("mimic.link"), bms, linkAttrs()) : row(t("mimic.pack"), bms, 'data-fmt="n2"');
    mimic.push(mimicBox("bms", t("mimic.bms"), rows.length ? rows : [only]));
  }
  root.innerHTML = `
    <h1 class="sr-only">${esc(t("nav.overview"))}</h1>
    ${mimic.length ? `<div class="mimic" aria-label="${esc(t("mimic.label"))}"><h2 class="sr-only">${esc(t("mimic.label"))}</h2>${mimic.join('<span class="wire" aria-hidden="true"></span>')}</div>` : ""}
    ${estop ? `<p id="estop-result" class="result" role="status" aria-live="polite" hidden></p>${estopDialog()}` : ""}
    <div class="tiles">${b.channels.map(channelTile).join("")}</div>`;
  bindEstop(root);
  const refresh = bindTags(root, app.live);
  const tiles = b.channels.map((ch) => [ch, $(`#tile-${CSS.escape(ch.name)}`, root)]);
  const paintAll = () => {
    tiles.forEach(([ch, el]) => paintTile(el, ch, app.live));
    paintEstopTrip(root, app.live);
  };
  paintAll();
  return {
    update(change) {
      if (change.kind === "tags") refresh(change.names);
      paintAll();
    },
  };
}
