"""``bgrl reproduce`` (the paper's simulated-feedback experiment), ``hf-sweep`` and ``compare``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from tqdm import tqdm

from services.cli.feedback_options import (
    DecoderAccuracyOption,
    DecodersOption,
    FeedbackOption,
    LabelChannelOption,
    feedback_factory,
    feedback_settings,
)
from services.cli.paths import output_folder, refuse_file

if TYPE_CHECKING:
    from services.learner.runs import RunFailure, RunRecord

MAX_SEED = 2**31 - 1
"""Largest seed a run takes (as the platform's jobs): JSON readers and CSV tools keep it exact."""
EXIT_INTERRUPTED = 130


def _split(value: str) -> list[str]:
    return [item.strip() for item in value.split(",") if item.strip()]


def _entries(value: str, option: str) -> list[str]:
    """A comma-separated option's entries: at least one, each once (a repeated entry would
    run, and count, the same runs twice)."""
    entries = _split(value)
    if not entries:
        raise typer.BadParameter("give at least one entry", param_hint=option)
    _each_once(entries, option)
    return entries


def _each_once(entries: list[Any], option: str) -> None:
    repeated = sorted({f"{e:g}" if isinstance(e, float) else str(e) for e in entries
                       if entries.count(e) > 1})  # fmt: skip
    if repeated:
        raise typer.BadParameter(
            f"each entry once: {', '.join(repeated)} repeated", param_hint=option
        )


def _accuracies(value: str, option: str = "--accuracies") -> list[float]:
    """Feedback accuracies C: numbers in [0, 1], each once."""
    values = []
    for entry in _entries(value, option):
        try:
            accuracy = float(entry)
        except ValueError:
            raise typer.BadParameter(f"{entry!r} is not a number", param_hint=option) from None
        if not 0.0 <= accuracy <= 1.0:  # also refuses nan
            raise typer.BadParameter(f"{entry!r} is not in [0, 1]", param_hint=option)
        values.append(accuracy)
    _each_once(values, option)
    return values


def parse_ppo_overrides(items: list[str]) -> dict[str, Any]:
    """``["n_epochs=10", "reward_scale=1"]`` -> typed PPOConfig overrides, each setting
    once, checked by the learner's rules (ValueError naming the setting)."""
    from services.learner.ppo import PPOConfig, check_settings
    from services.learner.specs import RUN_FIXED_PPO_FIELDS

    fields = {f.name for f in dataclasses.fields(PPOConfig)}
    defaults = PPOConfig()
    overrides: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not raw.strip():
            raise ValueError(f"--ppo expects KEY=VALUE, got {item!r}")
        if key in RUN_FIXED_PPO_FIELDS:
            raise ValueError(f"--ppo {key} is set per run by the experiment and cannot be changed")
        if key not in fields:
            known = sorted(fields - RUN_FIXED_PPO_FIELDS)
            raise ValueError(f"--ppo: unknown PPO setting {key!r}; known: {known}")
        if key in overrides:  # a factor study would silently take the last value
            raise ValueError(f"--ppo {key} given twice; give each setting once")
        default = getattr(defaults, key)
        try:
            if default is None:  # an optional number (target_kl): a float or "none"
                value = None if raw.strip().lower() == "none" else float(raw.strip())
            elif isinstance(default, bool):
                if raw.strip().lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                value: Any = raw.strip().lower() in ("true", "1")
            elif isinstance(default, tuple):
                value = tuple(int(v) for v in _split(raw))
            else:
                value = type(default)(raw.strip())
        except ValueError:
            kind = "number" if default is None else type(default).__name__
            raise ValueError(f"--ppo {key}: {raw!r} is not a valid {kind}") from None
        try:
            check_settings({key: value})
        except ValueError as exc:
            raise ValueError(f"--ppo {exc}") from None
        overrides[key] = value
    PPOConfig(**overrides)  # validates combinations (e.g. n_steps vs minibatch_size)
    return overrides


def reproduce(
    out: Annotated[Path, typer.Option(help="Output folder (results.json, CSV, plots).")],
    quick: Annotated[
        bool, typer.Option(help="2 seeds: a < 20 min check of every task and method.")
    ] = False,
    seeds: Annotated[
        int | None, typer.Option(min=1, help="Seeds per configuration (default 10, quick 2).")
    ] = None,
    first_seed: Annotated[int, typer.Option(min=0, max=MAX_SEED, help="First seed.")] = 0,
    workers: Annotated[int, typer.Option(min=1, help="Worker processes.")] = 2,
    tasks: Annotated[str, typer.Option(help="Comma-separated: sssg,vssg.")] = "sssg,vssg",
    methods: Annotated[
        str, typer.Option(help="Comma-separated: rl_sparse,rl_rich,rl_shaped,hf_sparse.")
    ] = "rl_sparse,rl_rich,hf_sparse",
    accuracies: Annotated[
        str, typer.Option(help="Comma-separated feedback accuracies C.")
    ] = "0.55,0.6,0.7",
    treatments: Annotated[
        str, typer.Option(help="HF-step treatments: authors,truncated_is.")
    ] = "authors",
    map_path: Annotated[
        Path | None, typer.Option("--map", help="Map JSON (default: the sim's default map).")
    ] = None,
    ppo: Annotated[
        list[str] | None,
        typer.Option(
            help="Override a PPO setting for every method, KEY=VALUE (repeatable), e.g. "
            "--ppo n_epochs=10 --ppo reward_scale=1 --ppo hf_guide_sampling=true."
        ),
    ] = None,
    preset: Annotated[
        str,
        typer.Option(
            help="paper: the paper's settings; platform: the recommended ones (HF steps "
            "truncated_is, hf_guide_sampling=true, sil_coef=1 for every method, the "
            "recommended stage-2 method)."
        ),
    ] = "paper",
    hf_method: Annotated[
        str | None,
        typer.Option(
            help="Stage-2 method of pi_HF (bgrl hf-sweep --method), in place of the "
            "preset's (paper: the paper's Fhat; platform: the recommended one)."
        ),
    ] = None,
    labels: Annotated[
        int,
        typer.Option(
            min=1,
            help="Labels each HF+sparse run learns pi_HF from (every labelled action; the "
            "paper's 1000). One count per output folder.",
        ),
    ] = 1000,
    single_run: Annotated[
        bool,
        typer.Option(
            "--single-run",
            help="Train each run alone instead of in lockstep batches (one per worker; "
            "the same records, several times slower).",
        ),
    ] = False,
    feedback: FeedbackOption = "oracle",
    decoder_accuracy: DecoderAccuracyOption = None,
    label_channel: LabelChannelOption = "hard",
    decoders: DecodersOption = "eegnet,lda,xdawn_rg",
) -> None:
    """Reproduce Fig. 3: RL-sparse, RL-rich, HF+sparse at several C, SSSG and VSSG.

    Runs train in lockstep batches, one per worker (docs/learner.md, "Lockstep sweeps"):
    each run's record is bit-identical to training it alone (``--single-run``).

    ``--preset platform`` replaces the default ``--treatments`` by truncated_is, adds
    ``--ppo hf_guide_sampling=true`` and ``--ppo sil_coef=1`` (self-imitation, every method
    alike) unless given, and learns pi_HF with the recommended stage-2 method
    (docs/stage2.md); ``--hf-method`` picks another stage-2 method.

    Exits with 1 naming the failed runs if any run fails (the others finish and are kept in
    results.json; the failed ones, with their tracebacks, under "failed"; a rerun retries
    them), with 2 on bad input.
    """
    from services.learner.hf_methods import get_method
    from services.learner.pool import reproduce as run_reproduction
    from services.learner.pool import validate_maps
    from services.learner.specs import (
        FULL_SEEDS,
        QUICK_SEEDS,
        apply_preset,
        build_specs,
        with_feedback,
    )

    n_seeds = seeds if seeds is not None else (QUICK_SEEDS if quick else FULL_SEEDS)
    if first_seed + n_seeds - 1 > MAX_SEED:
        raise typer.BadParameter(
            f"the last seed, {first_seed + n_seeds - 1}, is above {MAX_SEED}",
            param_hint="--first-seed",
        )
    task_list, method_list = _entries(tasks, "--tasks"), _entries(methods, "--methods")
    accuracy_list = feedback_settings(
        feedback, label_channel, decoder_accuracy, _accuracies(accuracies)
    )
    factory = feedback_factory(feedback, decoders, out)
    try:
        treatment_list, overrides, preset_method = apply_preset(
            preset, _entries(treatments, "--treatments"), parse_ppo_overrides(ppo or [])
        )
        hf_method = preset_method if hf_method is None else get_method(hf_method).name
        specs = build_specs(
            seeds=n_seeds,
            first_seed=first_seed,
            tasks=task_list,
            methods=method_list,
            accuracies=accuracy_list,
            treatments=treatment_list,
            map_path=None if map_path is None else str(map_path),
            ppo_overrides=overrides,
            hf_method=hf_method,
            n_labels=labels,
        )
        specs = with_feedback(specs, feedback, label_channel)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    try:
        validate_maps(specs)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--map") from None
    output_folder(out)
    with tqdm(total=len(specs), desc="reproduce", unit="run") as bar:

        def done(record: RunRecord) -> None:
            bar.set_postfix_str(f"{record.run_spec.label} SPL={record.final_spl:.2f}")
            bar.update(1)

        def failed(failure: RunFailure) -> None:
            bar.write(f"run failed: {failure}")
            bar.update(1)

        try:
            results = run_reproduction(
                out,
                specs,
                workers=workers,
                lockstep=not single_run,
                config_note={
                    "cli": {
                        "quick": quick,
                        "seeds": n_seeds,
                        "overrides": overrides,
                        "preset": preset,
                        "hf_method": hf_method,
                        "labels": labels,
                        "feedback": feedback,
                        "label_channel": label_channel,
                        **({} if factory is None else {"virtual_subject": factory.describe()}),
                    }
                },
                on_done=done,
                on_failure=failed,
                on_resume=bar.update,
                feedback_factory=factory,
            )
        except ValueError as exc:  # e.g. the folder holds runs with other settings
            raise typer.BadParameter(str(exc), param_hint="--out") from None
        except KeyboardInterrupt:
            bar.close()
            _interrupted(_kept_by_reproduction(out))
    typer.echo((out / "summary.md").read_text())
    typer.echo(f"wrote {out / 'results.json'}, results.csv, summary.md and fig3_*.png")
    _exit_on_failures(results.failed, out / "results.json")


def _interrupted(kept: str) -> None:
    """Ctrl-C: say what was ``kept`` and exit 130 (no traceback)."""
    typer.echo(f"interrupted: {kept}; run the same command again to resume", err=True)
    raise typer.Exit(EXIT_INTERRUPTED)


def _finished(count: int, where: Path) -> str:
    """E.g. ``2 finished run(s) kept in OUT/results.json`` (``no run finished`` if none)."""
    if count == 0:
        return f"no run finished (nothing kept in {where})"
    return f"{count} finished run(s) kept in {where}"


def _kept_by_reproduction(out: Path) -> str:
    """What an interrupted ``bgrl reproduce`` keeps: its finished runs (results.json) and
    the checkpoints of the unfinished ones (OUT/checkpoints, where they resume from)."""
    from services.learner.outputs import load_results
    from services.learner.pool import CHECKPOINT_FOLDER

    path, folder = out / "results.json", out / CHECKPOINT_FOLDER
    kept = _finished(len(load_results(path).runs) if path.is_file() else 0, path)
    n_checkpoints = len(list(folder.glob("*.pt"))) if folder.is_dir() else 0
    if n_checkpoints:
        kept += f"; {n_checkpoints} unfinished run(s) keep their checkpoints in {folder}"
    return kept


def _exit_on_failures(failures: list[RunFailure], where: Path) -> None:
    """Name every failed run on stderr and exit 1 (nothing to do if none failed)."""
    if not failures:
        return
    typer.echo(f"{len(failures)} run(s) failed (tracebacks under 'failed' in {where}):", err=True)
    for failure in failures:
        typer.echo(f"  {failure}", err=True)
    typer.echo("run the same command again to retry them", err=True)
    raise typer.Exit(1)


def hf_sweep(
    out: Annotated[Path, typer.Option(help="Output folder; writes hf_policies.json.")],
    seeds: Annotated[int, typer.Option(min=1, help="Seeds per task and C.")] = 10,
    workers: Annotated[int, typer.Option(min=1, help="Worker processes.")] = 1,
    tasks: Annotated[str, typer.Option(help="Comma-separated: sssg,vssg.")] = "sssg,vssg",
    accuracies: Annotated[
        str, typer.Option(help="Comma-separated feedback accuracies C.")
    ] = "0.55,0.6,0.7",
    labels: Annotated[
        str, typer.Option(help="Comma-separated label budgets N (every labelled action).")
    ] = "1000",
    method: Annotated[
        str,
        typer.Option(help="Comma-separated stage-2 methods (paper = the paper's Fhat)."),
    ] = "paper",
    feedback: FeedbackOption = "oracle",
    decoder_accuracy: DecoderAccuracyOption = None,
    label_channel: LabelChannelOption = "hard",
    decoders: DecodersOption = "eegnet,lda,xdawn_rg",
    single_run: Annotated[
        bool,
        typer.Option(
            "--single-run",
            help="Learn each pi_HF alone instead of in lockstep batches (the same rows, "
            "several times slower).",
        ),
    ] = False,
) -> None:
    """Stage 2 alone: pi_HF's SPL (greedy) and success (sampling) vs C, labels and method.

    Runs learn in lockstep batches, one or more per worker (docs/learner.md, "Lockstep
    sweeps"): each row is bit-identical to learning it alone (``--single-run``) but for
    its wall time. Writes hf_policies.json (one row per run, resumable; a folder holds one
    ``--decoders`` set), summary.md (the table) and spl_vs_labels.png.
    """
    from services.learner.hf_methods import get_method
    from services.learner.pool import hf_policy_sweep, load_sweep
    from services.learner.specs import TASK_ENV_IDS
    from services.learner.stage2_report import write_report

    task_list = _entries(tasks, "--tasks")
    accuracy_list = feedback_settings(
        feedback, label_channel, decoder_accuracy, _accuracies(accuracies)
    )
    factory = feedback_factory(feedback, decoders, out)
    methods = _entries(method, "--method")
    try:
        budgets = [int(n) for n in _entries(labels, "--labels")]
        if min(budgets) < 1:
            raise ValueError
    except ValueError:
        raise typer.BadParameter(f"--labels must be integers >= 1, got {labels!r}") from None
    _each_once(budgets, "--labels")
    try:
        for name in methods:
            get_method(name)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--method") from None
    unknown = sorted(set(task_list) - set(TASK_ENV_IDS))
    if unknown:
        raise typer.BadParameter(
            f"unknown task {unknown[0]!r}; expected one of {sorted(TASK_ENV_IDS)}",
            param_hint="--tasks",
        )
    output_folder(out)
    try:
        rows, failures = hf_policy_sweep(
            out,
            tasks=task_list,
            accuracies=accuracy_list,
            seeds=seeds,
            labels=budgets,
            methods=methods,
            workers=workers,
            on_failure=lambda failure: typer.echo(f"run failed: {failure}", err=True),
            feedback=feedback,
            label_channel=label_channel,
            feedback_factory=factory,
            lockstep=not single_run,
        )
    except ValueError as exc:  # e.g. the folder's hf_policies.json is not one
        raise typer.BadParameter(str(exc), param_hint="--out") from None
    except KeyboardInterrupt:
        path = out / "hf_policies.json"
        kept = load_sweep(path).rows if path.exists() else []
        if kept:
            write_report(out, kept)
        _interrupted(_finished(len(kept), path))
    write_report(out, rows)
    if rows:
        typer.echo((out / "summary.md").read_text())
        typer.echo(f"wrote {out / 'hf_policies.json'}, summary.md and spl_vs_labels.png")
    _exit_on_failures(failures, out / "hf_policies.json")


NSTAR_BUDGETS = "250,500,1000,2000,4000"


def hf_nstar(
    out: Annotated[Path, typer.Option(help="Output folder; writes nstar_rows.json, nstar.*.")],
    seeds: Annotated[
        str, typer.Option(help="Seeds as first-last (tuning range; 1000-1019 are reserved).")
    ] = "100-109",
    workers: Annotated[int, typer.Option(min=1, help="Worker processes.")] = 1,
    tasks: Annotated[str, typer.Option(help="Comma-separated: sssg,vssg.")] = "sssg,vssg",
    accuracies: Annotated[
        str, typer.Option(help="Comma-separated oracle accuracies C (--feedback oracle).")
    ] = "0.55,0.6,0.65,0.7,0.8",
    labels: Annotated[
        str, typer.Option(help="Comma-separated budgets (one collection to the largest).")
    ] = NSTAR_BUDGETS,
    method: Annotated[str, typer.Option(help="Comma-separated stage-2 methods.")] = "bayes_query",
    reference_draws: Annotated[
        int,
        typer.Option(
            min=0, help="Draws of the idealised reference per C and rule (0: no reference)."
        ),
    ] = 400,
    figure: Annotated[
        Path | None, typer.Option(help="Also copy the figure here (e.g. docs/figures/nstar.png).")
    ] = None,
    report_only: Annotated[
        bool, typer.Option(help="No new runs: the table, N* and figure of the rows in OUT.")
    ] = False,
    include: Annotated[
        list[Path] | None,
        typer.Option(
            help="hf_policies.json of a `bgrl hf-sweep` to add to the table (grouped by "
            "feedback and channel as the runs here)."
        ),
    ] = None,
    information: Annotated[
        Path | None,
        typer.Option(
            help="information.json of `bgrl eeg information` (default OUT/information.json "
            "if there): the bound per channel from the measured bits per label."
        ),
    ] = None,
    feedback: FeedbackOption = "oracle",
    decoder_accuracy: DecoderAccuracyOption = None,
    label_channel: LabelChannelOption = "hard",
    decoders: DecodersOption = "eegnet,lda,xdawn_rg",
) -> None:
    """N*(C): labels for >= 80 % useful pi_HF (greedy SPL >= 0.5) with Wilson 95 % intervals,
    the idealised Bayesian reference and the information bound per channel.

    The labels come from the noisy oracle at each C (hard labels), or with ``--feedback
    virtual_subject`` from each seed's virtual subject decoded end to end (C is then the
    decoder's target accuracy, ``--decoder-accuracy``; the quality searches are cached in
    OUT/virtual_subjects) through ``--label-channel`` hard or soft. Runs of several
    feedbacks and channels may share OUT: the table and N* are per feedback and channel.

    Writes nstar_rows.json (one row per run and budget, resumable; a folder holds one
    ``--decoders`` set), nstar.json, nstar.csv, nstar.md and nstar.png.
    """
    from services.learner.hf_methods import get_method
    from services.learner.nstar import (
        NStarJob,
        bounds,
        load_rows,
        reference_curves,
        row_key,
        run_jobs,
        series_label,
        write_outputs,
    )

    try:
        first, _, last = seeds.partition("-")
        seed_list = list(range(int(first), int(last or first) + 1))
        budgets = tuple(sorted(int(n) for n in _entries(labels, "--labels")))
        if not seed_list or min(budgets) < 1:
            raise ValueError
    except ValueError:
        raise typer.BadParameter("--seeds is first-last, --labels integers >= 1") from None
    methods = _entries(method, "--method")
    try:
        for name in methods:
            get_method(name)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--method") from None
    task_list = _entries(tasks, "--tasks")
    cs = feedback_settings(feedback, label_channel, decoder_accuracy, _accuracies(accuracies))
    factory = feedback_factory(feedback, decoders, out)
    virtual = feedback == "virtual_subject"
    output_folder(out)
    jobs = [
        NStarJob(
            task,
            None if virtual else c,
            seed,
            name,
            budgets,
            feedback,
            label_channel,
            c if virtual else None,
        )
        for c in cs
        for task in task_list
        for name in methods
        for seed in seed_list
    ]
    rows_path = out / "nstar_rows.json"
    try:
        if report_only:
            rows = load_rows(rows_path).rows if rows_path.exists() else []
        else:
            with typer.progressbar(length=len(jobs), label="collections") as bar:
                rows = run_jobs(
                    jobs, rows_path, workers, lambda job, new: bar.update(1),
                    feedback_factory=factory,
                )  # fmt: skip
    except ValueError as exc:  # e.g. the rows of another decoder set
        raise typer.BadParameter(str(exc), param_hint="--out") from None
    except KeyboardInterrupt:
        n_rows = len(load_rows(rows_path).rows) if rows_path.exists() else 0
        _interrupted(f"{n_rows} row(s) (a run at a budget each) kept in {rows_path}")
    grid = sorted({*budgets, *range(100, max(budgets) + 1, 100)})
    from services.learner.pool import load_sweep

    seen = {(*row_key(r), r["n_labels"]) for r in rows}
    decoder_set = _decoder_set(load_rows(rows_path).feedback_source, rows) if rows else None
    for path in include or []:
        try:
            sweep = load_sweep(path)
        except (OSError, ValueError) as exc:
            raise typer.BadParameter(f"{path}: {exc}", param_hint="--include") from None
        theirs = _decoder_set(sweep.feedback_source, sweep.rows)
        if theirs is not None and decoder_set is not None and theirs != decoder_set:
            raise typer.BadParameter(
                f"{path}: its virtual-subject rows were made with {theirs}, the table's with "
                f"{decoder_set}; a table holds one decoder set",
                param_hint="--include",
            )
        decoder_set = decoder_set or theirs
        for row in sweep.rows:
            key = (*row_key(row), row["n_labels"])
            if key not in seen:
                seen.add(key)
                rows.append({**row, "source": str(path)})
    # the reference runs on SSSG's oracle path (VSSG's starts jitter around the same start)
    params = {"path": "sssg", "accuracies": cs, "grid": grid, "draws": reference_draws}
    cache = out / "reference.json"  # reused while the reference's parameters are the same
    cached = json.loads(cache.read_text()) if cache.exists() else {}
    if reference_draws == 0:
        reference = []
    elif cached.get("params") == params:
        reference = cached["reference"]
    else:
        reference = reference_curves("sssg", cs, grid, reference_draws)
        cache.write_text(json.dumps({"params": params, "reference": reference}, indent=1))
    measured = _information_summary(information or out / "information.json", information)
    limits = [b for task in task_list for b in bounds(task, cs, measured)]
    result = write_outputs(out, rows, reference, limits, figure)
    for star in result["n_star"]:
        typer.echo(
            f"{series_label(star)}: N* = "
            + (str(star["n_star"]) if star["n_star"] else f"> {star['above']}")
        )
    typer.echo(f"wrote {out / 'nstar.json'}, nstar.csv and nstar.png")


def _decoder_set(
    feedback_source: dict[str, Any] | None, rows: list[dict[str, Any]]
) -> dict[str, Any] | None:
    """The settings of the virtual subjects behind ``rows`` (a folder's ``feedback_source``
    record; the default set for a folder written before the record); None if no row is
    a virtual subject's."""
    from services.learner.feedback_sources import recorded_feedback_source

    feedbacks = [row.get("feedback") for row in rows]
    if all(feedback in (None, "oracle") for feedback in feedbacks):
        return None

    def defaults() -> dict[str, Any]:
        from services.worker.e2e_feedback import VirtualSubjectFactory

        return VirtualSubjectFactory().describe_defaults()

    return recorded_feedback_source(feedback_source, feedbacks, defaults)


def _information_summary(path: Path, given: Path | None) -> list[dict[str, Any]]:
    """The per-target ``summary`` of a `bgrl eeg information` information.json (made from its
    rows while that command is still running); none when the default path holds none, a
    ``typer.BadParameter`` when a given one is not one."""
    from services.worker.label_information import summarize

    if given is None and not path.exists():
        return []
    try:
        document = json.loads(path.read_text())
        return list(document["summary"] if "summary" in document else summarize(document["rows"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise typer.BadParameter(
            f"{path}: not an information.json of `bgrl eeg information` ({exc!r})",
            param_hint="--information",
        ) from None


def compare(
    folders: Annotated[list[Path], typer.Argument(help="`bgrl reproduce` output folders.")],
    out: Annotated[Path, typer.Option(help="Output folder (compare.md/json, plots).")],
) -> None:
    """Factor studies side by side: a table and per-run plots over several reproductions."""
    from services.learner.outputs import compare_studies

    refuse_file(out)
    try:
        compare_studies(folders, out)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    except OSError as exc:  # e.g. --out below a file
        raise typer.BadParameter(f"{exc.filename}: {exc.strerror}", param_hint="--out") from None
    typer.echo((out / "compare.md").read_text())
    typer.echo(f"wrote {out / 'compare.md'}, compare.json and compare_*.png")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``reproduce``, ``hf-sweep`` and ``compare``."""
    app.command("reproduce")(reproduce)
    app.command("hf-sweep")(hf_sweep)
    app.command("hf-nstar")(hf_nstar)
    app.command("compare")(compare)
