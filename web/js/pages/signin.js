// Sign in: e-mail and password exchanged for an access token (POST /api/v1/auth/token).

import { signIn } from "../api.js";
import { h, messageBox } from "../dom.js";

function nextPath() {
  const next = new URLSearchParams(location.search).get("next") || "/subjects";
  // only paths of this site (no "//host" or absolute URLs)
  return next.startsWith("/") && !next.startsWith("//") ? next : "/subjects";
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
  email.focus();
}
