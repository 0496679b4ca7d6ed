// Attention on the shop floor: a prompt that waits or a batch that ended must be noticed by an
// operator who is at the next machine. A short tone made in the page (WebAudio oscillator: no audio
// file, nothing fetched) and a flashing title; a mute toggle that is a station preference
// (localStorage), not a person's.
"use strict";

const ATTN = {
  ctx: null,           // AudioContext, made on the first tap (browsers start audio only after a gesture)
  flashTimer: null,
  flashText: "",
  baseTitle: document.title,  // in the page's language once i18n.js has set it (DOMContentLoaded below)
  repeatTimer: null,
};

function attentionMuted() { return localStorage.getItem("station.mute") === "1"; }

function audioContext() {
  const Ctx = window.AudioContext || window.webkitAudioContext;
  if (!Ctx) return null;
  if (!ATTN.ctx) ATTN.ctx = new Ctx();
  if (ATTN.ctx.state === "suspended") ATTN.ctx.resume().catch(() => {});
  return ATTN.ctx;
}

// A few short tones: "prompt" rises (something to do), "end" falls (done).
function beep(kind) {
  if (attentionMuted()) return;
  const ctx = audioContext();
  if (!ctx) return;
  const notes = kind === "end" ? [880, 660, 440] : [660, 880];
  const t0 = ctx.currentTime + 0.02;
  notes.forEach((hz, i) => {
    const osc = ctx.createOscillator();
    const gain = ctx.createGain();
    osc.type = "square";
    osc.frequency.value = hz;
    const t = t0 + i * 0.18;
    gain.gain.setValueAtTime(0.0001, t);
    gain.gain.exponentialRampToValueAtTime(0.25, t + 0.02);
    gain.gain.exponentialRampToValueAtTime(0.0001, t + 0.16);
    osc.connect(gain).connect(ctx.destination);
    osc.start(t);
    osc.stop(t + 0.17);
  });
}

function flashTitle(text) {
  stopFlash();
  ATTN.flashText = text;
  let on = true;
  document.title = text;
  ATTN.flashTimer = setInterval(() => {
    on = !on;
    document.title = on ? text : ATTN.baseTitle;
  }, 1000);
}

function stopFlash() {
  clearInterval(ATTN.flashTimer);
  ATTN.flashTimer = null;
  ATTN.flashText = "";
  document.title = ATTN.baseTitle;
}

// kind "prompt": tone now (unless silent) and every 30 s while it waits, title "● Prompt waiting";
// kind "end": one tone, title "● Batch ended" until the operator touches the page.
function attention(kind, silent = false) {
  clearInterval(ATTN.repeatTimer);
  ATTN.repeatTimer = null;
  if (!silent) beep(kind);
  if (kind === "prompt") {
    flashTitle("● " + t("attention.prompt_waiting"));
    ATTN.repeatTimer = setInterval(() => beep("prompt"), 30000);
  } else {
    flashTitle("● " + t("attention.batch_ended"));
  }
  document.body.dataset.attention = kind;
}

function attentionDone(kind) {
  if (kind && document.body.dataset.attention !== kind) return;
  clearInterval(ATTN.repeatTimer);
  ATTN.repeatTimer = null;
  stopFlash();
  delete document.body.dataset.attention;
}

function renderMute() {
  const b = document.getElementById("mute");
  if (!b) return;
  const muted = attentionMuted();
  b.setAttribute("aria-pressed", muted ? "true" : "false");
  b.title = t(muted ? "attention.muted_title" : "attention.sound_title");
  b.classList.toggle("muted-on", muted);
  b.querySelector(".mute-word").textContent = t(muted ? "attention.muted" : "attention.sound");
}

function toggleMute() {
  if (attentionMuted()) localStorage.removeItem("station.mute"); else localStorage.setItem("station.mute", "1");
  renderMute();
  if (!attentionMuted()) beep("prompt");  // the operator hears what the tone is
}

document.addEventListener("DOMContentLoaded", () => {
  const b = document.getElementById("mute");
  if (b) b.addEventListener("click", toggleMute);
  I18N.ready.then(() => { ATTN.baseTitle = document.title; renderMute(); });  // the words once the catalog is in
  // the first tap unlocks audio; any tap or key ends the "batch ended" flash (the operator is here)
  const touched = () => {
    audioContext();
    if (document.body.dataset.attention === "end") attentionDone("end");
  };
  document.addEventListener("pointerdown", touched, true);
  document.addEventListener("keydown", touched, true);
});
