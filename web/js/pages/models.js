// Models and downloads: trained RL policies, human-feedback policies (pi_HF), ErrP classifiers,
// and the results files and plots jobs wrote.

import { all } from "../api.js";
import { downloadButton, fmtBytes, fmtDateTime, fmtNumber, h, shortId, table } from "../dom.js";

const fileName = (artifact) => artifact.relpath.split("/").pop();
const jobLink = (jobId) => (jobId ? shortId(jobId, `/jobs/${jobId}`) : "–");
/** The two policies a guided-PPO job keeps (the worker's file names). */
const POLICY_FILES = {
  "policy.pt": "best evaluation: the job's model",
  "policy_last.pt": "last step",
};

export async function modelsPage(root) {
  document.title = "Models · Brain-guided RL platform";
  const [policies, hfModels, classifiers, results, plots, subjects] = await Promise.all([
    all("/api/v1/artifacts", { kind: "model" }, 500),
    all("/api/v1/hf-models", {}, 500),
    all("/api/v1/classifiers", {}, 500),
    all("/api/v1/artifacts", { kind: "results" }, 500),
    all("/api/v1/artifacts", { kind: "plot" }, 500),
    all("/api/v1/subjects"),
  ]);
  const code = new Map(subjects.map((s) => [s.id, s.code]));
  root.append(
    h("h1", {}, "Models and downloads"),
    h("section", {}, h("h2", {}, "Trained policies (π_RL)"),
      h("p", { class: "muted" }, "A guided-PPO job keeps two: policy.pt, the policy of its best evaluation ",
        "(the job's model, what `bgrl models pull` fetches), and policy_last.pt, the policy at its last step."),
      table(policies, [
        { label: "Job", cell: (a) => jobLink(a.job_id) },
        { label: "File", cell: (a) => fileName(a) },
        {
          label: "Which",
          cell: (a) => (POLICY_FILES[fileName(a)]
            ? h("span", { class: fileName(a) === "policy.pt" ? "badge best" : "badge" }, POLICY_FILES[fileName(a)])
            : "–"),
        },
        { label: "Size", cell: (a) => fmtBytes(a.size_bytes) },
        { label: "Made", cell: (a) => fmtDateTime(a.created_at) },
        {
          label: "",
          cell: (a) => a.job_id && fileName(a) === "policy.pt"
            ? downloadButton("Download", `/api/v1/jobs/${a.job_id}/model`, `policy-${a.job_id}.pt`)
            : downloadButton("Download", `/api/v1/artifacts/${a.id}/download`, fileName(a)),
        },
      ], { empty: "No trained policies yet: submit a guided-PPO job." })),
    h("section", {}, h("h2", {}, "Human-feedback policies (π_HF)"),
      table(hfModels, [
        { label: "Name", cell: (m) => m.name },
        { label: "Task", cell: (m) => m.task.toUpperCase() },
        { label: "Feedback accuracy", cell: (m) => fmtNumber(m.feedback_accuracy) },
        { label: "Labels", cell: (m) => m.n_labels ?? "–" },
        { label: "Job", cell: (m) => jobLink(m.job_id) },
        {
          label: "",
          cell: (m) => [
            m.torchscript_artifact_id ? downloadButton("TorchScript", `/api/v1/hf-models/${m.id}/download?format=torchscript`, `hf-model-${m.id}.pt`) : null,
            m.onnx_artifact_id ? downloadButton("ONNX", `/api/v1/hf-models/${m.id}/download?format=onnx`, `hf-model-${m.id}.onnx`) : null,
          ],
        },
      ], { empty: "No stored human-feedback policies." })),
    h("section", {}, h("h2", {}, "ErrP classifiers"),
      table(classifiers, [
        { label: "Name", cell: (c) => h("a", { href: `/classifiers/${c.id}` }, c.name) },
        { label: "Subject", cell: (c) => (c.subject_id ? h("a", { href: `/subjects/${c.subject_id}` }, code.get(c.subject_id) || `#${c.subject_id}`) : "–") },
        { label: "Balanced accuracy", cell: (c) => fmtNumber(c.metrics.balanced_accuracy) },
        { label: "ROC AUC", cell: (c) => fmtNumber(c.metrics.roc_auc) },
        {
          label: "",
          cell: (c) => [
            c.onnx_artifact_id ? downloadButton("ONNX", `/api/v1/classifiers/${c.id}/download?format=onnx`, `classifier-${c.id}.onnx`) : null,
            c.torchscript_artifact_id ? downloadButton("TorchScript", `/api/v1/classifiers/${c.id}/download?format=torchscript`, `classifier-${c.id}.pt`) : null,
          ],
        },
      ], { empty: "No classifiers yet: a calibration job makes one." })),
    h("section", {}, h("h2", {}, "Results and plots"),
      table([...results, ...plots].sort((a, b) => b.created_at.localeCompare(a.created_at)), [
        { label: "File", cell: (a) => fileName(a) },
        { label: "Kind", cell: (a) => a.kind },
        { label: "Job", cell: (a) => jobLink(a.job_id) },
        { label: "Size", cell: (a) => fmtBytes(a.size_bytes) },
        { label: "", cell: (a) => downloadButton("Download", `/api/v1/artifacts/${a.id}/download`, fileName(a)) },
      ], { empty: "No results files yet: a reproduction or calibration job writes them." })),
  );
}
