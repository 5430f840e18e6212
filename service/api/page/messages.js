// One line per message under the header: errors stay until dismissed or replaced by the same
// kind of action, notes fade after a few seconds.

const NOTE_SECONDS = 4;

function box() {
  return document.getElementById("messages");
}

function add(text, kind) {
  const item = document.createElement("p");
  item.className = `message ${kind}`;
  item.textContent = text;
  const close = document.createElement("button");
  close.type = "button";
  close.className = "close";
  close.textContent = "×";
  close.title = "dismiss";
  close.addEventListener("click", () => item.remove());
  item.append(close);
  box().append(item);
  return item;
}

/** An error the user must see: the server's own message (ApiError) or ours. */
export function showError(error, context = "") {
  const text = error && error.message ? error.message : String(error);
  const item = add(context ? `${context}: ${text}` : text, "error");
  if (error && error.status) item.dataset.status = String(error.status);
  return item;
}

export function showNote(text) {
  const item = add(text, "note");
  setTimeout(() => item.remove(), NOTE_SECONDS * 1000);
  return item;
}

export function clearErrors() {
  box().querySelectorAll(".message.error").forEach((item) => item.remove());
}
