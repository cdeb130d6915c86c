// The dashboard's entry point: who is signed in, the navigation bar, and the page for the path.

import { get, signOutToSignIn, toSignIn, token } from "./api.js";
import { h } from "./dom.js";
import { accountPage } from "./pages/account.js";
import { auditPage, rigsPage, usersPage } from "./pages/admin.js";
import { classifierPage } from "./pages/classifier.js";
import { jobPage } from "./pages/job.js";
import { jobsPage } from "./pages/jobs.js";
import { displayPage } from "./pages/display.js";
import { livePage } from "./pages/live.js";
import { modelsPage } from "./pages/models.js";
import { recordingsPage } from "./pages/recordings.js";
import { sessionsPage } from "./pages/sessions.js";
import { signinPage } from "./pages/signin.js";
import { subjectPage } from "./pages/subject.js";
import { subjectsPage } from "./pages/subjects.js";

const ROUTES = [
  [/^\/(?:subjects)?$/, "subjects", subjectsPage],
  [/^\/subjects\/(\d+)$/, "subjects", subjectPage],
  [/^\/sessions$/, "sessions", sessionsPage],
  [/^\/sessions\/(\d+)\/live$/, "sessions", livePage],
  [/^\/sessions\/(\d+)\/display$/, "sessions", displayPage],
  [/^\/jobs$/, "jobs", jobsPage],
  [/^\/jobs\/([A-Za-z0-9_-]+)$/, "jobs", jobPage],
  [/^\/models$/, "models", modelsPage],
  [/^\/classifiers\/(\d+)$/, "models", classifierPage],
  [/^\/recordings$/, "recordings", recordingsPage],
  [/^\/account$/, "account", accountPage],
  [/^\/admin\/users$/, "users", usersPage],
  [/^\/admin\/rigs$/, "rigs", rigsPage],
  [/^\/admin\/audit$/, "audit", auditPage],
];

const LISTS = {
  subjects: ["/subjects", "Subjects"],
  sessions: ["/sessions", "Sessions"],
  jobs: ["/jobs", "Jobs"],
  models: ["/models", "Models"],
  recordings: ["/recordings", "Recordings"],
  account: ["/account", "Your account"],
  users: ["/admin/users", "Users"],
  rigs: ["/admin/rigs", "Rigs"],
  audit: ["/admin/audit", "Audit log"],
};
const MAX_ROW_ID = 2 ** 31 - 1; // the API's largest id: beyond it nothing can exist

/** A page for a path or an id that does not exist: what is missing and a way back. */
function notFound(root, text, section = "subjects") {
  const [href, label] = LISTS[section];
  document.title = "Not found · Brain-guided RL platform";
  root.replaceChildren(
    h("h1", {}, "Not found"),
    h("p", { class: "message error", role: "alert" }, text),
    h("p", {}, h("a", { href }, `Back to ${label}`)),
  );
}

let section = "subjects"; // the section of the page being shown (for its "not found")

function showAccount(user) {
  const box = document.getElementById("account");
  const button = h("button", { type: "button", class: "btn small" }, "Sign out");
  button.addEventListener("click", () => signOutToSignIn());
  box.replaceChildren(
    h("a", { class: "who", href: "/account", "data-nav": "account", title: "Your account: password, API tokens" },
      user.email, " ", h("span", { class: "badge" }, user.role)),
    button,
  );
  // admin pages are offered to admins only (the API refuses them to the others anyway)
  for (const item of document.querySelectorAll("[data-admin]")) {
    if (user.role === "admin") item.hidden = false;
    else item.remove();
  }
}

async function main() {
  const root = document.getElementById("main");
  const path = location.pathname.replace(/\/+$/, "") || "/";
  if (path === "/signin") {
    document.title = "Sign in · Brain-guided RL platform";
    signinPage(root);
    return;
  }
  if (!token()) {
    toSignIn();
    return;
  }
  const user = await get("/api/v1/users/me");
  showAccount(user);
  const route = ROUTES.find(([pattern]) => pattern.test(path));
  if (!route) {
    notFound(root, `There is no page ${path} here.`);
    return;
  }
  const [pattern, routeSection, render] = route;
  section = routeSection;
  for (const link of document.querySelectorAll("[data-nav]")) {
    if (link.dataset.nav === section) link.setAttribute("aria-current", "page");
  }
  const params = pattern.exec(path).slice(1);
  const badId = params.find((p) => /^\d+$/.test(p) && !(Number(p) >= 1 && Number(p) <= MAX_ROW_ID));
  if (badId !== undefined) {
    notFound(root, `No ${path.split("/")[1].replace(/s$/, "")} has the id ${badId}.`, section);
    return;
  }
  const context = {
    user,
    canEdit: user.role === "staff" || user.role === "admin",
    query: new URLSearchParams(location.search),
  };
  root.replaceChildren();
  await render(root, context, ...params);
}

main().catch((err) => {
  if (err.status === 401) return; // on the way to the sign-in page
  const root = document.getElementById("main");
  if (err.status === 404) {
    notFound(root, err.message, section); // e.g. "no job with id …" (an old or mistyped link)
    return;
  }
  document.title = "Error · Brain-guided RL platform";
  root.replaceChildren(
    h("h1", {}, "Something went wrong"),
    h("p", { class: "message error", role: "alert" }, err.message),
  );
});
