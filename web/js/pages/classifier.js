// Calibration results: an ErrP classifier's metrics, confusion matrix and the calibration
// report (ERP waveforms, topographies, training curves) its job wrote.

import { all, get, imageUrl } from "../api.js";
import { downloadButton, fmtDateTime, fmtNumber, h, shortId, table } from "../dom.js";

function confusionMatrix(cm) {
  if (!Array.isArray(cm) || cm.length !== 2) return null;
  const labels = ["correct", "error"];
  return h("table", { class: "grid confusion" },
    h("caption", {}, "Test confusion matrix (rows: true label, columns: decoded)"),
    h("thead", {}, h("tr", {}, h("td"), labels.map((l) => h("th", { scope: "col" }, l)))),
    h("tbody", {}, cm.map((row, i) => h("tr", {}, h("th", { scope: "row" }, labels[i]),
      row.map((v) => h("td", { class: "num" }, v))))));
}

export async function classifierPage(root, _context, classifierId) {
  const clf = await get(`/api/v1/classifiers/${classifierId}`);
  document.title = `Classifier ${clf.id} · Brain-guided RL platform`;
  const artifacts = clf.job_id ? await all("/api/v1/artifacts", { job_id: clf.job_id }) : [];
  const subject = clf.subject_id ? await get(`/api/v1/subjects/${clf.subject_id}`) : null;
  const m = clf.metrics;
  const scalar = Object.entries(m).filter(([, v]) => typeof v === "number" || typeof v === "boolean");
  const report = artifacts.find((a) => a.relpath.endsWith("report.png"));
  const figure = report
    ? h("img", { class: "plot", src: await imageUrl(`/api/v1/artifacts/${report.id}/download`),
      alt: "Calibration report: ErrP grand averages, topographies, training curves, confusion matrix" })
    : h("p", { class: "muted" }, "This classifier's job wrote no report figure.");
  root.append(
    h("p", { class: "crumbs" }, h("a", { href: "/models" }, "Models"), " / classifier ", clf.id),
    h("h1", {}, `Calibration: ${clf.name}`),
    h("p", { class: "muted" }, `Made ${fmtDateTime(clf.created_at)}`,
      subject ? [" · subject ", h("a", { href: `/subjects/${subject.id}` }, subject.code)] : "",
      clf.job_id ? [" · job ", shortId(clf.job_id, `/jobs/${clf.job_id}`)] : ""),
    h("div", { class: "columns" },
      h("section", {}, h("h2", {}, "Metrics"),
        table(scalar, [
          { label: "Metric", cell: ([k]) => k.replaceAll("_", " ") },
          { label: "Value", cell: ([, v]) => (typeof v === "number" && !Number.isInteger(v) ? fmtNumber(v, 3) : String(v)) },
        ])),
      h("section", {}, confusionMatrix(m.confusion_matrix),
        h("h2", {}, "Downloads"),
        clf.onnx_artifact_id || clf.torchscript_artifact_id || artifacts.length ? null
          : h("p", { class: "muted" }, "No files stored for this classifier."),
        h("ul", { class: "plain" },
          clf.onnx_artifact_id ? h("li", {}, downloadButton("ONNX", `/api/v1/classifiers/${clf.id}/download?format=onnx`, `classifier-${clf.id}.onnx`)) : null,
          clf.torchscript_artifact_id ? h("li", {}, downloadButton("TorchScript", `/api/v1/classifiers/${clf.id}/download?format=torchscript`, `classifier-${clf.id}.pt`)) : null,
          artifacts.filter((a) => /\.(json|html|png)$/.test(a.relpath)).map((a) =>
            h("li", {}, downloadButton(a.relpath.split("/").pop(), `/api/v1/artifacts/${a.id}/download`, a.relpath.split("/").pop())))))),
    h("section", {}, h("h2", {}, "Report"), figure),
  );
}
