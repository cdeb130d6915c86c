// The job submission form, generated from each kind's JSON Schema (GET /api/v1/job-kinds, the
// job contract's pydantic models): a new kind needs no change here. Types, bounds, defaults,
// enums and descriptions come from the schema; nested settings (e.g. PPO's) fold into a
// collapsible section; two extension keywords say more: ``x-shown-when`` (a field that
// applies only while sibling fields hold given values) and ``x-references`` (the id of an
// item of GET /api/v1/<collection>, offered as a choice). Checked as the user types against
// the schema; the API's refusals (422) appear at the field they name.

import { all, ApiError, get, post } from "../api.js";
import { field, h, messageBox, oneAtATime } from "../dom.js";

let kindsAnswer = null;

/** Every job kind with its config schema (asked once per page). */
export function jobKinds() {
  kindsAnswer ??= get("/api/v1/job-kinds");
  return kindsAnswer;
}

/** The stage-2 methods that learn pi_HF (the choices of a config's ``hf_method``; the live
 *  session start takes the same), from the kinds' schemas. */
export function stage2Methods(kinds) {
  for (const k of kinds) {
    const prop = k.config_schema?.properties?.hf_method;
    if (prop) return resolve(prop, k.config_schema)[0].enum || [];
  }
  return [];
}

const fmt = (n) => (Number.isFinite(n) ? n.toLocaleString("en") : String(n));

/** The first paragraph of a schema description, without reStructuredText's double quotes. */
function prose(text) {
  return (text || "").split("\n\n")[0].replace(/``/g, "").replace(/\s+/g, " ").trim();
}

/** A property's schema with ``anyOf: [X, null]`` and ``$ref`` resolved: [schema, nullable]. */
function resolve(prop, root) {
  let schema = prop;
  let nullable = false;
  if (Array.isArray(prop.anyOf)) {
    const others = prop.anyOf.filter((s) => s.type !== "null");
    nullable = others.length < prop.anyOf.length;
    const { anyOf, ...outer } = prop;
    schema = others.length === 1 ? { ...others[0], ...outer } : prop;
  }
  if (schema.$ref) {
    const name = schema.$ref.split("/").pop();
    const { $ref, ...outer } = schema;
    schema = { ...root.$defs[name], ...outer };
  }
  return [schema, nullable];
}

/** Why a number breaks the schema's bounds, or null. */
function boundsError(n, s) {
  if (s.type === "integer" && !Number.isInteger(n)) return "must be a whole number";
  const low = s.minimum ?? s.exclusiveMinimum;
  const high = s.maximum ?? s.exclusiveMaximum;
  const tooLow = s.minimum !== undefined ? n < s.minimum : s.exclusiveMinimum !== undefined && n <= s.exclusiveMinimum;
  const tooHigh = s.maximum !== undefined ? n > s.maximum : s.exclusiveMaximum !== undefined && n >= s.exclusiveMaximum;
  if (!tooLow && !tooHigh) return null;
  if (low !== undefined && high !== undefined) {
    const open = s.exclusiveMinimum !== undefined ? " (not " + fmt(low) + ")" : "";
    return `must be between ${fmt(low)} and ${fmt(high)}${open}`;
  }
  if (tooLow) return s.exclusiveMinimum !== undefined ? `must be more than ${fmt(low)}` : `must be at least ${fmt(low)}`;
  return `must be at most ${fmt(high)}`;
}

/** What a reference's item is called in a choice: "#3 S-014" (its name, code or file). */
function itemLabel(item) {
  const name = item.name ?? item.code ?? item.filename ?? "";
  const task = item.task ? ` (${String(item.task).toUpperCase()})` : "";
  return `#${item.id} ${name}${task}`.trim();
}

/**
 * One control per schema property. Each has ``node`` (what the form shows), ``raw()`` (the
 * value as typed, for x-shown-when), ``read()`` -> {given, value, error} and ``setError``.
 * A value is sent when the field is required, was prefilled or was changed by the user
 * (an untouched default is left to the API, which fills it in: a preset's "unless given"
 * stays true).
 */
function control(name, prop, { root, required, prefill, references, prefix }) {
  const [s, nullable] = resolve(prop, root);
  const path = prefix + name; // the input's name: "ppo.n_steps", as the API's errors name it
  // pydantic titles a field without one "N Steps": the setting's own name says more
  const automatic = name.split("_").map((w) => w.charAt(0).toUpperCase() + w.slice(1)).join(" ");
  const title = !s.title || (s.title === automatic && name.includes("_")) ? name : s.title;
  const hint = prose(s.description);
  const hasDefault = s.default !== undefined && s.default !== null;
  let touched = prefill !== undefined;
  const touch = () => { touched = true; };
  const initial = prefill !== undefined ? prefill : s.default;

  if (s.type === "object" && s.properties) {
    const group = objectControls(s, { root, prefill: prefill || {}, references, prefix: `${path}.` });
    const error = h("span", { class: "field-error", "aria-live": "polite" });
    const node = h("details", { class: "config-group", "data-field": path, open: prefill !== undefined },
      h("summary", {}, title), hint ? h("p", { class: "hint" }, hint) : null, group.nodes, error);
    return {
      name, node, children: group.controls,
      raw: () => null,
      read() {
        const { value, errors } = group.read();
        return { given: Object.keys(value).length > 0, value, errors };
      },
      setError(message) {
        error.textContent = message || "";
        if (message) node.open = true;
      },
      update: group.update,
    };
  }

  let input;
  let raw;
  let parse;
  if (s["x-references"]) {
    const items = references.get(s["x-references"]) || [];
    const blank = required ? "Choose…" : "(default)";
    input = h("select", { name: path },
      h("option", { value: "" }, blank),
      items.map((item) => h("option", { value: item.id }, itemLabel(item))));
    if (initial !== undefined && initial !== null && !items.some((i) => String(i.id) === String(initial))) {
      input.append(h("option", { value: initial }, `#${initial}`));
    }
    if (initial !== undefined && initial !== null) input.value = String(initial);
    raw = () => (input.value === "" ? null : Number(input.value));
    parse = () => (raw() === null && required ? { error: "required" } : { value: raw() });
  } else if (s.enum) {
    const options = s.enum.map((v) => h("option", { value: v }, v));
    const blank = nullable || (!required && !hasDefault) ? [h("option", { value: "" }, "(default)")] : [];
    input = h("select", { name: path }, blank, options);
    if (initial !== undefined && initial !== null) input.value = initial;
    raw = () => (input.value === "" ? null : input.value);
    parse = () => ({ value: raw() });
  } else if (s.type === "boolean" && !nullable) {
    input = h("input", { type: "checkbox", name: path, checked: initial === true || initial === "true" });
    raw = () => input.checked;
    parse = () => ({ value: input.checked });
  } else if (s.type === "boolean") {
    input = h("select", { name: path }, h("option", { value: "" }, "(default)"),
      h("option", { value: "true" }, "yes"), h("option", { value: "false" }, "no"));
    if (initial === true || initial === false) input.value = String(initial);
    raw = () => (input.value === "" ? null : input.value === "true");
    parse = () => ({ value: raw() });
  } else if (s.type === "array" && s.items?.enum) {
    const checked = Array.isArray(initial) ? initial : [];
    const boxes = s.items.enum.map((v) => h("input", { type: "checkbox", name: path, value: v, checked: checked.includes(v) }));
    input = h("fieldset", { class: "checks" }, h("legend", {}, title),
      boxes.map((box) => h("label", {}, box, ` ${box.value}`)));
    raw = () => boxes.filter((b) => b.checked).map((b) => b.value);
    parse = () => {
      const value = raw();
      if (s.minItems && value.length < s.minItems) return { error: `choose at least ${s.minItems}` };
      return { value };
    };
  } else if (s.type === "array") {
    const items = s.items || {};
    input = h("input", { name: path, value: Array.isArray(initial) ? initial.join(", ") : "",
      placeholder: "comma-separated" });
    raw = () => input.value;
    parse = () => {
      const parts = input.value.split(",").map((v) => v.trim()).filter(Boolean);
      if (!parts.length) return required || touched ? { error: "give at least one value, comma-separated" } : { value: null };
      const value = [];
      for (const part of parts) {
        const n = items.type === "integer" || items.type === "number" ? Number(part) : part;
        if (typeof n === "number") {
          if (Number.isNaN(n)) return { error: `${part} is not a number` };
          const bad = boundsError(n, items);
          if (bad) return { error: `each value ${bad}: not ${part}` };
        }
        value.push(n);
      }
      if (s.minItems && value.length < s.minItems) return { error: `give at least ${s.minItems}` };
      if (s.maxItems && value.length > s.maxItems) return { error: `give at most ${s.maxItems}` };
      return { value };
    };
  } else if (s.type === "integer" || s.type === "number") {
    input = h("input", {
      type: "number", name: path, step: s.type === "integer" ? 1 : "any", inputmode: s.type === "integer" ? "numeric" : "decimal",
      min: s.minimum ?? s.exclusiveMinimum, max: s.maximum ?? s.exclusiveMaximum,
      value: initial ?? "", placeholder: hasDefault ? "" : "default",
    });
    raw = () => (input.value === "" ? null : Number(input.value));
    parse = () => {
      if (input.value === "") {
        // a number input holding text the browser cannot read reports "" and badInput
        if (input.validity?.badInput) return { error: "must be a number" };
        return required ? { error: "required" } : { value: null };
      }
      const n = Number(input.value);
      const bad = boundsError(n, s);
      return bad ? { error: bad } : { value: n };
    };
  } else {
    input = h("input", { name: path, value: initial ?? "", maxlength: s.maxLength });
    raw = () => input.value;
    parse = () => (input.value === "" && required ? { error: "required" } : { value: input.value || null });
  }
  input.addEventListener("input", touch);
  input.addEventListener("change", touch);
  const wrapper = input.tagName === "FIELDSET"
    ? h("div", { class: "field" }, input, hint ? h("span", { class: "hint" }, hint) : null)
    : field(title, input, hint);
  if (input.tagName === "FIELDSET") {
    const error = h("span", { class: "field-error", "aria-live": "polite" });
    wrapper.append(error);
    wrapper.setError = (message) => { error.textContent = message || ""; };
  }
  if (s.type === "boolean" && !nullable) wrapper.classList.add("check-field");
  wrapper.dataset.field = path;
  return {
    name, node: wrapper, shownWhen: s["x-shown-when"],
    raw,
    read() {
      const { value, error } = parse();
      if (error) return { given: true, value: null, errors: { [name]: error } };
      const given = value !== null && value !== undefined && (required || touched);
      return { given, value, errors: {} };
    },
    setError: (message) => wrapper.setError(message),
  };
}

/** The controls of an object schema's properties, with x-shown-when applied among them. */
function objectControls(schema, { root, prefill, references, prefix = "" }) {
  const required = new Set(schema.required || []);
  const controls = Object.entries(schema.properties).map(([name, prop]) =>
    control(name, prop, { root, required: required.has(name), prefill: prefill[name], references, prefix }));
  const byName = new Map(controls.map((c) => [c.name, c]));
  const shown = (c) => !c.shownWhen || Object.entries(c.shownWhen).every(([other, values]) => {
    const current = byName.get(other)?.raw() ?? null;
    return values.some((v) => (v === null ? current === null : String(v) === String(current)));
  });
  return {
    controls,
    nodes: controls.map((c) => c.node),
    update() {
      for (const c of controls) {
        c.node.hidden = !shown(c);
        c.update?.();
      }
    },
    read() {
      const value = {};
      const errors = {};
      for (const c of controls) {
        if (!shown(c)) continue;
        const got = c.read();
        for (const [key, message] of Object.entries(got.errors)) errors[c.children ? `${c.name}.${key}` : key] = message;
        if (got.given) value[c.name] = got.value;
      }
      return { value, errors };
    },
  };
}

/** Every control by its dotted path ("ppo.n_steps"). */
function byPath(controls, prefix = "") {
  const out = new Map();
  for (const c of controls) {
    out.set(prefix + c.name, c);
    if (c.children) for (const [k, v] of byPath(c.children, `${prefix}${c.name}.`)) out.set(k, v);
  }
  return out;
}

/** The items each x-references of the schemas names (GET /api/v1/<collection>), but for
 *  the ``fixed`` fields. */
async function referenceItems(kinds, fixed) {
  const names = new Set();
  const walk = (value) => {
    if (Array.isArray(value)) value.forEach(walk);
    else if (value && typeof value === "object") {
      if (typeof value["x-references"] === "string") names.add(value["x-references"]);
      Object.values(value).forEach(walk);
    }
  };
  for (const k of kinds) {
    const { properties, ...rest } = k.config_schema;
    walk(rest); // $defs
    walk(Object.entries(properties).filter(([name]) => !(name in fixed)).map(([, prop]) => prop));
  }
  const lists = await Promise.all([...names].map((n) => all(`/api/v1/${n}`).catch(() => [])));
  return new Map([...names].map((n, i) => [n, lists[i]]));
}

/**
 * The submission form of the submittable ``kinds`` (``GET /api/v1/job-kinds``' answer).
 * Options: ``kind`` preselected, ``values`` prefilled (e.g. from a session's page),
 * ``fixed`` sent as they are and not shown (e.g. the recording a row calibrates),
 * ``title``/``submitLabel``/``compact`` for where it is shown; ``onSubmitted(job, message)``
 * is called with the API's new job.
 */
export async function jobForm(kinds, { kind = null, values = {}, fixed = {}, title = "Submit a job",
  submitLabel = "Submit job", compact = false, onSubmitted = () => {} } = {}) {
  const offered = kinds.filter((k) => k.submittable);
  const references = await referenceItems(offered, fixed);
  const select = h("select", { name: "kind", id: compact ? null : "job-kind" },
    offered.map((k) => h("option", { value: k.name }, k.title)));
  if (kind) select.value = kind;
  const about = h("p", { class: "hint" });
  const body = h("div", { class: "job-config" });
  const message = messageBox();
  const submit = h("button", { type: "submit", class: compact ? "btn primary small" : "btn primary" }, submitLabel);
  const form = h("form", {
    class: compact ? "inline-form job-form" : "card job-form", id: compact ? null : "job-form", novalidate: true,
    "aria-label": compact ? title : null, "aria-labelledby": compact ? null : "job-form-title",
  },
  compact ? null : h("h2", { id: "job-form-title" }, title),
  offered.length > 1 ? field("Kind", select) : null, about, body, submit, message);

  let current = null; // {kind, group, paths}
  function build() {
    const chosen = offered.find((k) => k.name === select.value) || offered[0];
    const schema = chosen.config_schema;
    const shown = { ...schema, properties: Object.fromEntries(
      Object.entries(schema.properties).filter(([name]) => !(name in fixed))) };
    const group = objectControls(shown, { root: schema, prefill: chosen.name === kind ? values : {}, references });
    current = { kind: chosen.name, group, paths: byPath(group.controls) };
    about.textContent = prose(schema.description);
    body.replaceChildren(...group.nodes);
    message.clear();
    group.update();
  }
  /** Client-side check: errors at their fields; returns the config, or null. */
  function check({ quiet = false } = {}) {
    current.group.update();
    const { value, errors } = current.group.read();
    // while the user types, a field left empty is not yet an error (it is on submit)
    for (const [path, c] of current.paths) c.setError(quiet && errors[path] === "required" ? "" : errors[path] || "");
    return Object.keys(errors).length ? null : { ...value, ...fixed };
  }
  /** The API's refusal at the field it names (``config.ppo.n_steps``; a rule of the whole
   *  config, ``config``, at the first field its message names) and below the form. */
  function showRefusal(err) {
    for (const c of current.paths.values()) c.setError("");
    if (err instanceof ApiError) {
      for (const [name, text] of Object.entries(err.fields)) {
        let path = name.replace(/^config\.?/, "");
        while (path && !current.paths.has(path)) path = path.split(".").slice(0, -1).join(".");
        if (!path) path = firstNamed(text);
        current.paths.get(path)?.setError(text);
      }
    }
    message.error(err);
  }

  /** The shown field whose name comes first in ``text`` (the outer one of equals). */
  function firstNamed(text) {
    let best = "";
    let at = Infinity;
    for (const [path, c] of current.paths) {
      if (c.node.closest("[hidden]")) continue;
      const found = new RegExp(`\\b${path.split(".").pop()}\\b`).exec(text);
      if (found && found.index <= at) {
        best = found.index < at || path.length < best.length ? path : best;
        at = found.index;
      }
    }
    return best;
  }

  select.addEventListener("change", build);
  form.addEventListener("input", () => check({ quiet: true }));
  form.addEventListener("change", () => check({ quiet: true }));
  form.addEventListener("submit", oneAtATime([submit], async () => {
    message.clear();
    const config = check();
    if (config === null) {
      message.show("Correct the fields marked above.", "error");
      return null;
    }
    try {
      const job = await post("/api/v1/jobs", { kind: current.kind, config });
      onSubmitted(job, message);
    } catch (err) {
      showRefusal(err);
    }
    return null;
  }));
  build();
  return form;
}
