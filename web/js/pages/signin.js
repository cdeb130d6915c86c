// Sign in: e-mail and password exchanged for an access token (POST /api/v1/auth/token).

import { signIn, takeSignInReason } from "../api.js";
import { h, messageBox } from "../dom.js";

/** Where to go after signing in: ``?next=`` if it is a page of this site, else /subjects.
 *  Resolved as the browser would, so "/\\host", "/\t/host" or "//host" cannot lead away. */
export function nextPath(search = location.search) {
  const next = new URLSearchParams(search).get("next") || "";
  if (!next.startsWith("/")) return "/subjects";
  let url;
  try {
    url = new URL(next, location.origin);
  } catch {
    return "/subjects";
  }
  if (url.origin !== location.origin || url.pathname.startsWith("//")) return "/subjects";
  return url.pathname + url.search + url.hash;
}

export function signinPage(root) {
  document.querySelector(".nav")?.setAttribute("hidden", "");
  const email = h("input", {
    id: "email", name: "email", type: "email", autocomplete: "username", required: true,
  });
  const password = h("input", {
    id: "password", name: "password", type: "password", autocomplete: "current-password",
    required: true,
  });
  const message = messageBox();
  const submit = h("button", { type: "submit", class: "btn primary" }, "Sign in");
  const form = h(
    "form",
    { class: "card narrow", method: "post", action: "/api/v1/auth/token" },
    h("h1", {}, "Sign in"),
    h("div", { class: "field" }, h("label", { for: "email" }, "E-mail"), email),
    h("div", { class: "field" }, h("label", { for: "password" }, "Password"), password),
    submit,
    message,
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    submit.disabled = true;
    message.clear();
    try {
      await signIn(email.value.trim(), password.value);
      location.assign(nextPath());
    } catch (err) {
      message.error(err);
      password.select();
      submit.disabled = false;
    }
  });
  root.replaceChildren(form);
  const reason = takeSignInReason(); // e.g. the access token expired or was revoked
  if (reason) message.show(reason, "warning");
  email.focus();
}
