// The job submission form: a guided-PPO run or a reproduction sweep, checked as the user types
// against the API's limits (POST /api/v1/jobs; services/api/schemas/jobs.py).

import { ApiError, post } from "../api.js";
import { field, h, messageBox } from "../dom.js";

export const LIMITS = {
  maxTotalSteps: 2_000_000,
  maxSeed: 2 ** 31 - 1,
  maxRuns: 2000,
  defaultNSteps: 128,
  defaultMinibatch: 64,
};

/** Stage-2 methods that learn pi_HF (docs/stage2.md); the API's HF_METHOD_NAMES. */
export const HF_METHODS = [
  ["paper", "paper (the paper's Fhat)"],
  ["noise_aware", "noise_aware"],
  ["categorical", "categorical"],
  ["thompson", "thompson"],
  ["categorical_thompson", "categorical_thompson"],
  ["categorical_info", "categorical_info"],
  ["categorical_onpolicy", "categorical_onpolicy"],
  ["categorical_kernel", "categorical_kernel"],
];

function intIn(value, min, max, name) {
  if (value === "") return null;
  const n = Number(value);
  if (!Number.isInteger(n)) return `${name} must be a whole number`;
  if (n < min || n > max) return `${name} must be between ${min} and ${max.toLocaleString("en")}`;
  return null;
}

function numberInput(name, attrs = {}) {
  return h("input", { type: "number", name, inputmode: "numeric", ...attrs });
}

function checkboxes(name, options, checked) {
  return h(
    "fieldset",
    { class: "checks" },
    h("legend", {}, name),
    options.map(([value, label]) =>
      h("label", {}, h("input", { type: "checkbox", name, value, checked: checked.includes(value) }), ` ${label}`),
    ),
  );
}

const checked = (fieldset) => [...fieldset.querySelectorAll("input:checked")].map((i) => i.value);

/** PPO settings both kinds share; returns {fields, values(), errors(totalSteps)}. */
function ppoFields() {
  const nSteps = numberInput("n_steps", { min: 1, max: 100000, placeholder: String(LIMITS.defaultNSteps) });
  const minibatch = numberInput("minibatch_size", { min: 1, max: 100000, placeholder: String(LIMITS.defaultMinibatch) });
  const epochs = numberInput("n_epochs", { min: 1, max: 1000, placeholder: "default" });
  const evalEvery = numberInput("eval_every", { min: 1, max: LIMITS.maxTotalSteps, placeholder: "default" });
  const fields = {
    n_steps: field("PPO n_steps", nSteps, "Steps per update (default 128)."),
    minibatch_size: field("Minibatch size", minibatch, "Divides n_steps (default 64)."),
    n_epochs: field("Epochs per update", epochs),
    eval_every: field("Evaluate every (steps)", evalEvery),
  };
  return {
    fields,
    values() {
      const ppo = {};
      for (const [key, f] of Object.entries(fields)) if (f.input.value !== "") ppo[key] = Number(f.input.value);
      return ppo;
    },
    errors(totalSteps) {
      const errors = {
        n_steps: intIn(nSteps.value, 1, 100000, "n_steps"),
        minibatch_size: intIn(minibatch.value, 1, 100000, "minibatch size"),
        n_epochs: intIn(epochs.value, 1, 1000, "epochs"),
        eval_every: intIn(evalEvery.value, 1, LIMITS.maxTotalSteps, "eval_every"),
      };
      const n = nSteps.value === "" ? LIMITS.defaultNSteps : Number(nSteps.value);
      const mb = minibatch.value === "" ? LIMITS.defaultMinibatch : Number(minibatch.value);
      if (!errors.n_steps && !errors.minibatch_size && n % mb) {
        errors.minibatch_size = `n_steps (${n}) must be a multiple of the minibatch size (${mb})`;
      }
      if (!errors.n_steps && Number.isInteger(totalSteps) && totalSteps < n) {
        errors.n_steps = `n_steps (${n}) may not exceed the total steps (${totalSteps})`;
      }
      return errors;
    },
  };
}

/** The settings preset of a run or a reproduction (the API's ``preset``). */
function presetSelect() {
  return h("select", { name: "preset" }, h("option", { value: "paper" }, "paper: the paper's settings"),
    h("option", { value: "platform" }, "platform: the recommended ones"));
}

function guidedForm(hfModels) {
  const task = h("select", { name: "task" }, h("option", { value: "sssg" }, "SSSG"), h("option", { value: "vssg" }, "VSSG"));
  const method = h("select", { name: "method" },
    [["rl_sparse", "RL, sparse reward"], ["rl_rich", "RL, rich reward"], ["hf_sparse", "HF-guided, sparse reward"]]
      .map(([v, l]) => h("option", { value: v }, l)));
  const accuracy = h("input", { type: "number", name: "accuracy", min: 0, max: 1, step: 0.01, value: "0.7" });
  const hfModel = h("select", { name: "hf_model_id" }, h("option", { value: "" }, "Train one from simulated feedback"),
    hfModels.map((m) => h("option", { value: m.id }, `${m.name} (${m.task.toUpperCase()})`)));
  const hfMethod = h("select", { name: "hf_method" }, h("option", { value: "" }, "Recommended (default)"),
    HF_METHODS.map(([v, l]) => h("option", { value: v }, l)));
  const nLabels = numberInput("n_labels", { min: 1, max: 1_000_000, value: "1000" });
  const seed = numberInput("seed", { min: 0, max: LIMITS.maxSeed, value: "0" });
  const totalSteps = numberInput("total_steps", { min: 1, max: LIMITS.maxTotalSteps, value: "40000", step: 1 });
  const preset = presetSelect();
  const ppo = ppoFields();
  const fields = {
    task: field("Task", task),
    method: field("Method", method),
    accuracy: field("Feedback accuracy C", accuracy, "0 to 1; the simulated feedback's accuracy."),
    hf_model_id: field("Human-feedback policy", hfModel),
    hf_method: field("Stage-2 method", hfMethod, "How pi_HF is learned from the labels (docs/stage2.md)."),
    n_labels: field("Feedback labels", nLabels, "1 to 1,000,000"),
    seed: field("Seed", seed),
    total_steps: field("Total steps", totalSteps, `1 to ${LIMITS.maxTotalSteps.toLocaleString("en")}`),
    preset: field("Preset", preset,
      "platform: HF steps truncated IS instead of authors, guide sampling, self-imitation."),
    ...ppo.fields,
  };
  const hfOnly = [fields.accuracy, fields.hf_model_id, fields.n_labels];
  return {
    fields,
    update() {
      for (const f of hfOnly) f.hidden = method.value !== "hf_sparse";
      // a stored pi_HF was learned with its own method
      fields.hf_method.hidden = method.value !== "hf_sparse" || hfModel.value !== "";
    },
    errors() {
      const total = Number(totalSteps.value);
      const errors = {
        seed: intIn(seed.value, 0, LIMITS.maxSeed, "seed") || (seed.value === "" ? "seed is required" : null),
        total_steps: intIn(totalSteps.value, 1, LIMITS.maxTotalSteps, "total steps") ||
          (totalSteps.value === "" ? "total steps are required" : null),
        ...ppo.errors(total),
      };
      if (method.value === "hf_sparse") {
        const c = accuracy.value === "" ? null : Number(accuracy.value);
        if (c === null && !hfModel.value) errors.accuracy = "HF-guided runs need C (or a stored policy)";
        else if (c !== null && !(c >= 0 && c <= 1)) errors.accuracy = "C must be between 0 and 1";
        errors.n_labels = intIn(nLabels.value, 1, 1_000_000, "labels");
      }
      return errors;
    },
    body() {
      const config = { task: task.value, method: method.value, seed: Number(seed.value), total_steps: Number(totalSteps.value),
        preset: preset.value };
      if (method.value === "hf_sparse") {
        if (accuracy.value !== "") config.accuracy = Number(accuracy.value);
        if (hfModel.value) config.hf_model_id = Number(hfModel.value);
        else if (hfMethod.value) config.hf_method = hfMethod.value;
        config.n_labels = Number(nLabels.value);
      }
      const overrides = ppo.values();
      if (Object.keys(overrides).length) config.ppo = overrides;
      return { kind: "guided_ppo", config };
    },
  };
}

function reproduceForm() {
  const quick = h("input", { type: "checkbox", name: "quick" });
  const seeds = numberInput("seeds", { min: 1, max: 100, placeholder: "10 (2 if quick)" });
  const firstSeed = numberInput("first_seed", { min: 0, max: LIMITS.maxSeed, value: "0" });
  const tasks = checkboxes("Tasks", [["sssg", "SSSG"], ["vssg", "VSSG"]], ["sssg", "vssg"]);
  const methods = checkboxes("Methods", [["rl_sparse", "RL sparse"], ["rl_rich", "RL rich"], ["hf_sparse", "HF sparse"]],
    ["rl_sparse", "rl_rich", "hf_sparse"]);
  const accuracies = h("input", { name: "accuracies", value: "0.55, 0.6, 0.7" });
  const nLabels = numberInput("n_labels", { min: 1, max: 1_000_000, value: "1000" });
  const treatments = checkboxes("HF treatments", [["authors", "authors"], ["truncated_is", "truncated IS"]], ["authors"]);
  const totalSteps = numberInput("total_steps", { min: 1, max: LIMITS.maxTotalSteps, value: "40000" });
  const preset = presetSelect();
  const ppo = ppoFields();
  const runs = h("p", { class: "hint", "aria-live": "polite" });
  const fields = {
    quick: field("Quick (2 seeds)", quick),
    seeds: field("Seeds per configuration", seeds, "1 to 100"),
    first_seed: field("First seed", firstSeed),
    tasks: h("div", { class: "field" }, tasks),
    methods: h("div", { class: "field" }, methods),
    accuracies: field("Accuracies C", accuracies, "Comma-separated, each 0 to 1 (HF runs)."),
    n_labels: field("Feedback labels", nLabels, "Labels each HF run learns pi_HF from; 1 to 1,000,000 (the paper: 1000)."),
    treatments: h("div", { class: "field" }, treatments),
    preset: field("Preset", preset,
      "platform: HF steps truncated IS instead of authors, guide sampling, self-imitation, the recommended stage-2 method."),
    total_steps: field("Steps per run", totalSteps),
    ...ppo.fields,
  };
  for (const key of ["tasks", "methods", "treatments"]) {
    const error = h("span", { class: "field-error", "aria-live": "polite" });
    fields[key].append(error);
    fields[key].setError = (m) => { error.textContent = m || ""; };
  }
  const parseAccuracies = () => accuracies.value.split(",").map((v) => v.trim()).filter(Boolean).map(Number);
  return {
    fields,
    extra: runs,
    update() {},
    errors() {
      const errors = {
        seeds: intIn(seeds.value, 1, 100, "seeds"),
        first_seed: intIn(firstSeed.value, 0, LIMITS.maxSeed, "first seed"),
        n_labels: intIn(nLabels.value, 1, 1_000_000, "labels") || (nLabels.value === "" ? "labels are required" : null),
        total_steps: intIn(totalSteps.value, 1, LIMITS.maxTotalSteps, "steps per run") ||
          (totalSteps.value === "" ? "steps per run are required" : null),
        ...ppo.errors(Number(totalSteps.value)),
        tasks: checked(tasks).length ? null : "choose at least one task",
        methods: checked(methods).length ? null : "choose at least one method",
        treatments: checked(treatments).length ? null : "choose at least one treatment",
      };
      const cs = parseAccuracies();
      if (!cs.length || cs.some((c) => !(c >= 0 && c <= 1))) errors.accuracies = "give accuracies between 0 and 1, comma-separated";
      const nSeeds = seeds.value === "" ? (quick.checked ? 2 : 10) : Number(seeds.value);
      const perSeed = checked(methods).reduce(
        (sum, m) => sum + (m === "hf_sparse" ? cs.length * checked(treatments).length : 1), 0,
      ) * checked(tasks).length;
      const total = perSeed * nSeeds;
      runs.textContent = Number.isFinite(total) ? `This sweep is ${total} run(s) of ${Number(totalSteps.value).toLocaleString("en")} steps.` : "";
      if (total > LIMITS.maxRuns) errors.seeds = `${total} runs; a reproduction may have ${LIMITS.maxRuns}`;
      return errors;
    },
    body() {
      const config = {
        quick: quick.checked,
        first_seed: Number(firstSeed.value || 0),
        tasks: checked(tasks),
        methods: checked(methods),
        accuracies: parseAccuracies(),
        n_labels: Number(nLabels.value),
        treatments: checked(treatments),
        preset: preset.value,
        ppo: { total_steps: Number(totalSteps.value), ...ppo.values() },
      };
      if (seeds.value !== "") config.seeds = Number(seeds.value);
      return { kind: "reproduce", config };
    },
  };
}

/** The submission form; ``onSubmitted(job)`` is called with the API's new job. */
export function jobForm(hfModels, onSubmitted) {
  const kinds = { guided_ppo: guidedForm(hfModels), reproduce: reproduceForm() };
  const kind = h("select", { name: "kind", id: "job-kind" },
    h("option", { value: "guided_ppo" }, "Guided-PPO run"), h("option", { value: "reproduce" }, "Reproduction sweep (Fig. 3)"));
  const body = h("div");
  const message = messageBox();
  const submit = h("button", { type: "submit", class: "btn primary" }, "Submit job");
  const form = h("form", { class: "card", id: "job-form", novalidate: true, "aria-labelledby": "job-form-title" },
    h("h2", { id: "job-form-title" }, "Submit a job"), field("Kind", kind), body, submit, message);

  const current = () => kinds[kind.value];
  function check() {
    const form = current();
    form.update();
    const errors = form.errors();
    for (const [key, f] of Object.entries(form.fields)) f.setError?.(f.hidden ? null : errors[key]);
    const valid = Object.entries(errors).every(([key, e]) => !e || form.fields[key]?.hidden);
    submit.disabled = !valid;
    return valid;
  }
  function show() {
    const form = current();
    body.replaceChildren(...Object.values(form.fields), form.extra || "");
    message.clear();
    check();
  }
  kind.addEventListener("change", show);
  form.addEventListener("input", check);
  form.addEventListener("change", check);
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    if (!check()) return;
    message.clear();
    submit.disabled = true;
    try {
      const job = await post("/api/v1/jobs", current().body());
      message.show(`Job ${job.id.slice(0, 8)} queued.`);
      onSubmitted(job);
    } catch (err) {
      if (err instanceof ApiError) {
        for (const [name, text] of Object.entries(err.fields)) {
          const key = name.replace(/^config\.(ppo\.)?/, "");
          current().fields[key]?.setError?.(text);
        }
      }
      message.error(err);
    } finally {
      submit.disabled = false;
    }
  });
  show();
  return form;
}
