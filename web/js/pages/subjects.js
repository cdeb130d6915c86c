// Subjects: search by code, register a new one (staff).

import { ApiError, get, post } from "../api.js";
import { field, fmtDateTime, h, messageBox, oneAtATime, table } from "../dom.js";

const PAGE = 50;
const CODE_PATTERN = "[A-Za-z0-9][A-Za-z0-9_.\\-]{0,63}";

function createForm(onCreated) {
  const code = h("input", { id: "new-subject-code", name: "code", required: true, pattern: CODE_PATTERN, maxlength: 64 });
  const notes = h("textarea", { name: "notes", rows: 3, maxlength: 10000 });
  const codeField = field("Code", code, "Pseudonymous, e.g. S01 (never a name).");
  const notesField = field("Notes", notes);
  const message = messageBox();
  const submit = h("button", { type: "submit", class: "btn primary" }, "Create subject");
  const form = h(
    "form",
    { class: "card", "aria-labelledby": "new-subject" },
    h("h2", { id: "new-subject" }, "New subject"),
    codeField,
    notesField,
    submit,
    message,
  );
  code.addEventListener("input", () => {
    codeField.setError(
      code.value && !code.validity.valid
        ? "Letters, digits, '_', '.', '-'; starts with a letter or digit; at most 64."
        : "",
    );
  });
  form.addEventListener("submit", oneAtATime([submit], async () => {
    message.clear();
    codeField.setError("");
    notesField.setError("");
    try {
      const subject = await post("/api/v1/subjects", {
        code: code.value.trim(),
        notes: notes.value,
      });
      message.show(`Subject ${subject.code} created.`);
      form.reset();
      onCreated(subject);
    } catch (err) {
      if (err instanceof ApiError) {
        codeField.setError(err.fields.code);
        notesField.setError(err.fields.notes);
      }
      message.error(err);
    }
  }));
  return form;
}

export async function subjectsPage(root, { canEdit, query }) {
  document.title = "Subjects · Brain-guided RL platform";
  const search = h("input", {
    type: "search", name: "code", id: "subject-search", value: query.get("code") || "",
    autocomplete: "off",
  });
  const list = h("div", { "aria-live": "polite" });
  const pager = h("div", { class: "pager" });
  let offset = 0;

  async function load() {
    const page = await get("/api/v1/subjects", {
      code: search.value.trim(), limit: PAGE, offset,
    });
    list.replaceChildren(
      table(
        page.items,
        [
          { label: "Code", cell: (s) => h("a", { href: `/subjects/${s.id}` }, s.code) },
          { label: "Notes", cell: (s) => h("span", { class: "clip" }, s.notes || "") },
          { label: "Registered", cell: (s) => fmtDateTime(s.created_at) },
        ],
        { caption: `${page.total} subject(s)`, empty: "No subject matches." },
      ),
    );
    const prev = h("button", { type: "button", class: "btn small", disabled: offset === 0 }, "Previous");
    const next = h(
      "button",
      { type: "button", class: "btn small", disabled: offset + PAGE >= page.total },
      "Next",
    );
    prev.addEventListener("click", () => { offset = Math.max(0, offset - PAGE); load(); });
    next.addEventListener("click", () => { offset += PAGE; load(); });
    pager.replaceChildren(page.total > PAGE ? [prev, " ", next] : []);
  }

  let timer = null;
  search.addEventListener("input", () => {
    clearTimeout(timer);
    timer = setTimeout(() => { offset = 0; load(); }, 200);
  });

  root.replaceChildren(
    h("h1", {}, "Subjects"),
    h(
      "div",
      { class: "columns" },
      h(
        "section",
        { class: "wide" },
        h(
          "form",
          { role: "search", class: "inline", onsubmit: (e) => { e.preventDefault(); load(); } },
          h("label", { for: "subject-search" }, "Search by code"),
          search,
        ),
        list,
        pager,
      ),
      canEdit ? h("aside", {}, createForm(() => load())) : null,
    ),
  );
  await load();
}
