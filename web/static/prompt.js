// The operator prompt ("turn the plate to N"): its text, a picture of the position asked for
// (orientation.js), and two answers: "Done: continue" and "Cannot do it" with the operator's words,
// which end the DUTs it concerns as error. Uses app.js (S, $, api, message, pollBatch, canControl)
// and attention.js (tone and title while it waits); its words from i18n.js (t).
"use strict";

// ---- prompts ---------------------------------------------------------------------------------
function promptId(p) { return p.prompt_id ?? p.id; }

function showPrompt(p) {
  const open = !$("prompt-banner").classList.contains("hidden");
  if (S.prompt && promptId(S.prompt) === promptId(p) && open) {
    if (p.direction && !S.prompt.direction) { S.prompt = p; drawPromptPicture(p); }  // the status has the exact one
    return;
  }
  S.prompt = p;
  S.promptShownAt = performance.now();
  $("prompt-text").replaceChildren(...promptWords(p));
  drawPromptPicture(p);
  $("prompt-cannot-box").classList.add("hidden");
  $("prompt-note").value = "";
  $("prompt-note").classList.remove("invalid");
  $("prompt-cannot-msg").textContent = "";
  $("prompt-banner").classList.remove("hidden");
  for (const id of ["prompt-confirm", "prompt-cannot", "prompt-cannot-send"]) $(id).disabled = !canControl();
  attention("prompt", S.alertedPrompt === promptId(p));  // one tone per prompt, even if a stale status hid it a moment
  S.alertedPrompt = promptId(p);
}

// The prompt in the page's language: the daemon's text is English ("turn the plate to N", a re-prompt
// "s03 still faces P 40 s after Done: turn the plate to N", station/daemon/positioning.py); a
// turn-the-plate prompt is said from its position, the re-prompt's reason kept as the station's words.
// English: the daemon's text as it is. Another prompt: its text, marked untranslated.
function promptWords(p) {
  const text = String(p.text || "");
  if (I18N.lang === "en") return [text];
  const m = /^(?:(.*): )?turn the plate to (\S+)$/.exec(text);
  const pos = p.position_name || (m && m[2]) || (m ? positionNameOf(p) : "");
  if ((p.kind === "turn_plate" || m) && pos) {
    const why = p.reason || (m && m[1]) || "";
    const main = t(p.again || why ? "prompt.turn_plate_again" : "prompt.turn_plate", { position: pos });
    if (!why) return [main];
    const detail = el("span", { class: "reason-detail prompt-why", lang: "en" }, why);
    return [main, el("br"), detail];
  }
  return reasonNodes(null, text);
}

function drawPromptPicture(p) {
  const pic = promptPicture(p);  // orientation.js
  $("prompt-picture").innerHTML = pic ? pic.svg : "";  // markup built from numbers and an escaped name
  $("prompt-picture").classList.toggle("hidden", !pic);
  $("prompt-words").textContent = pic ? `${pic.name}: ${pic.words}` : "";
}

function hidePrompt() {
  S.prompt = null;
  $("prompt-banner").classList.add("hidden");
  attentionDone("prompt");
}

async function answerPrompt(answer, note) {
  if (!S.prompt || !S.batchId) return false;
  const body = { prompt_id: promptId(S.prompt), answer };
  if (note !== undefined) body.note = note;
  try {
    await api(`/api/batches/${S.batchId}/prompt`, { method: "POST", body });
    hidePrompt();
    return true;
  } catch (e) {
    message(t(answer === "cannot" ? "prompt.could_not_send" : "prompt.confirm_failed", { why: e.message }));
    return false;
  }
}

async function confirmPrompt() {
  $("prompt-confirm").disabled = true;
  if (!(await answerPrompt("done"))) $("prompt-confirm").disabled = false;
}

// "Cannot do it": the operator's words are required; the DUTs the prompt concerns end as error with them.
async function sendCannot() {
  const note = $("prompt-note").value.trim();
  if (!note) {
    $("prompt-note").classList.add("invalid");
    $("prompt-cannot-msg").textContent = t("prompt.say_why");
    $("prompt-note").focus();
    return;
  }
  $("prompt-note").classList.remove("invalid");
  $("prompt-cannot-msg").textContent = "";
  $("prompt-cannot-send").disabled = true;
  if (await answerPrompt("cannot", note)) {
    message(t("prompt.answered_cannot"));
    pollBatch();
  }
  $("prompt-cannot-send").disabled = !canControl();
}

document.addEventListener("DOMContentLoaded", () => {
  $("prompt-confirm").addEventListener("click", confirmPrompt);
  $("prompt-cannot").addEventListener("click", () => {
    $("prompt-cannot-box").classList.remove("hidden");
    $("prompt-note").focus();
  });
  $("prompt-cannot-back").addEventListener("click", () => $("prompt-cannot-box").classList.add("hidden"));
  $("prompt-cannot-send").addEventListener("click", sendCannot);
  $("prompt-note").addEventListener("keydown", (e) => { if (e.key === "Enter") { e.preventDefault(); sendCannot(); } });
  $("prompt-note").addEventListener("input", () => { if ($("prompt-note").value.trim()) $("prompt-note").classList.remove("invalid"); });
});
