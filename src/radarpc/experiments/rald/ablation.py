"""RaLD's ablation studies (the seed's Tables 1, 3, 4 and 9): arms of stage-1 / stage-2 configs and
a generation config, each trained, generated and scored, one portable result row per arm.

A study YAML names its arms, the ColoRadar root, the split and ``every``::

    name: rald-table3
    data: data/sim_colo                 # the root, as `radarpc train --data` takes it
    split: test
    every: 10                           # score every 10th paired frame of each run
    arms:
      - name: c-encoder-cfar            # a row id (letters, digits, . _ -)
        label: "(c) w/ encoder, w/ CFAR init"
        autoencoder: ../../rald-ae-s.yaml          # stage-1 experiment YAML, relative to this file
        diffusion: ../../rald-s.yaml               # stage-2 YAML; leave out: the autoencoder's reconstruction
        generate: ../generate-official.yaml        # generation YAML; leave out: the official defaults
      - name: a-no-encoder
        autoencoder: ../../rald-ae-s.yaml
        diffusion: rald-s-no-encoder.yaml
        generate: ../generate-official.yaml
      - name: finetuned                 # fine-tunes arm c-encoder-cfar's stage 2 (the seed's Tables 6, 8)
        autoencoder: ../../rald-ae-s.yaml
        diffusion: ../generalization/rald-s-finetune.yaml   # rald-s with scenes: [lab, outdoor], 300 steps
        init: c-encoder-cfar

An arm with ``init: ARM`` (an earlier arm) starts its last stage from that arm's best weights
instead of fresh ones (:func:`~radarpc.experiments.rald.train.train_diffusion`'s ``init``): with a
diffusion config, ARM's stage 2 (both arms must name the same stage-1 config: a fine-tuned
diffusion model keeps its autoencoder); without one, ARM's stage 1; the two stages' models must be
the same network (checked when the study is read). Its stage folder's ``HASH`` and its row's key
include what it starts from (ARM's folder, ARM's configs and ARM's own ``init``). The configs' ``scenes`` say
which scene types each stage trains on; the others are held out, and the per-scene table shows
them zero-shot (an arm trained without them) and fine-tuned (an arm with ``init``).

:func:`run_rald_ablation` works through the arms in order. For an arm without its result row it
trains the arm's stage 1 into ``OUT/stage1/NAME-HASH`` and its stage 2 into
``OUT/stage2/NAME-HASH`` (:func:`~radarpc.experiments.rald.train.train_autoencoder`,
:func:`~radarpc.experiments.rald.train.train_diffusion`; ``HASH`` of the resolved config, and for
stage 2 of its stage-1 folder too, so arms with the same stage 1 share one run, and a finished
run returns at once; with ``stages``, ``STAGES/stage1/...`` and ``STAGES/stage2/...``, so that
studies naming the same configs, such as the reference arm of Tables 3, 4 and 9, share one
trained run), generates (or, without a diffusion config, reconstructs) the split into
``OUT/preds/ARM`` (:func:`~radarpc.experiments.rald.generation.generate_run`), scores it as
``radarpc evaluate-points`` does (:func:`radarpc.pipelines.point_eval.evaluate_folders`: CD and
EMD per scene) and writes ``OUT/results/ARM.json``: the arm, its key (the resolved configs, the
root's folder name, split, ``every``, the EMD subset size), the metrics per scene and over all
frames, the runs' status and their validation row at the best weights (stage 2's holds the radar
check, ``val_radar_gain``), the command, config file and software (commit). **An arm whose row is
present with the same key is finished** and neither trained nor generated again; every step
below it resumes on its own (a killed training from its last checkpoint, a killed generation
frame by frame). A row whose key differs is refused, naming the fields: remove the row (and the
arm's folders) to run it again.

:func:`write_rald_report` turns the rows into a Table-3-like Markdown table (``radarpc report
OUT``): per arm, CD and EMD (means over the scored frames) per scene and over all frames.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from radarpc.config import from_dict, load_yaml_mapping, to_dict
from radarpc.eval.pointsets import EMD_POINTS
from radarpc.experiments.rald.config import AutoencoderExperiment, DiffusionExperiment, experiment_from_dict
from radarpc.experiments.rald.generation import GenerateConfig, generate_run
from radarpc.experiments.rald.train import train_autoencoder, train_diffusion
from radarpc.experiments.study.provenance import provenance
from radarpc.experiments.study.results import RESULTS_DIR, flat_differences, plain_json, read_rows, write_named_row
from radarpc.io import atomic_write

__all__ = ["RALD_ROW_FORMAT", "RALD_ROW_FIELDS", "RALD_REPORT_MD", "RaldArm", "RaldAblationConfig", "ArmPlan",
           "load_rald_ablation", "arm_key", "run_rald_ablation", "write_rald_report"]

RALD_ROW_FORMAT = "radarpc rald ablation row 1"
"""The ``format`` every row of a RaLD ablation states."""
RALD_ROW_FIELDS = ("format", "run", "study", "arm", "key", "metrics")
"""What every such row holds."""
RALD_REPORT_MD = "report.md"

_NAME = re.compile(r"[A-Za-z0-9_.-]+")


@dataclass(frozen=True)
class RaldArm:
    """One arm: its stage configs (paths relative to the study file) and its generation."""

    name: str                           # row id and folder name: letters, digits, '.', '_', '-'
    autoencoder: str                    # stage-1 experiment YAML (stage: autoencoder)
    diffusion: str | None = None        # stage-2 experiment YAML; None: score the autoencoder's reconstruction
    generate: str | None = None         # generation YAML (radarpc generate --config); None: the official defaults
    label: str | None = None            # the table's row label; None: the name
    init: str | None = None             # an earlier arm whose last stage this arm's last stage fine-tunes

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not _NAME.fullmatch(self.name):
            raise ValueError(f"arm name {self.name!r}: use letters, digits, '.', '_' and '-' (it names a folder "
                             f"and a result row)")


@dataclass(frozen=True)
class RaldAblationConfig:
    """A RaLD ablation study (module docstring)."""

    name: str
    data: str                           # the ColoRadar root (relative to the working directory)
    arms: tuple[RaldArm, ...]
    split: str = "test"                 # the split generated and scored
    every: int = 1                      # every K-th paired frame of each run (1: all)
    emd_points: int = EMD_POINTS        # EMD subset size (evaluate-points' --emd-points)

    def __post_init__(self) -> None:
        if not self.arms:
            raise ValueError(f"study {self.name!r}: arms: give at least one arm")
        names = [a.name for a in self.arms]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"study {self.name!r}: arm name(s) {', '.join(twice)} given twice")
        for k in ("every", "emd_points"):
            v = getattr(self, k)
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise ValueError(f"study {self.name!r}: {k} must be an integer >= 1, got {v!r}")


@dataclass(frozen=True)
class ArmPlan:
    """An arm with its configs read: what runs where (folders relative to the study output)."""

    arm: RaldArm
    order: int
    autoencoder: AutoencoderExperiment
    diffusion: DiffusionExperiment | None
    generate: GenerateConfig
    stage1_dir: str                     # "stage1/NAME-HASH"
    stage2_dir: str | None              # "stage2/NAME-HASH", None without a diffusion config
    init: "ArmPlan | None" = None       # the arm whose last stage this one fine-tunes

    @property
    def label(self) -> str:
        return self.arm.label or self.arm.name

    @property
    def preds_dir(self) -> str:
        return f"preds/{self.arm.name}"


def _digest(value) -> str:
    return hashlib.sha256(json.dumps(plain_json(value), sort_keys=True).encode()).hexdigest()[:10]


def _read_experiment(path: Path, stage: str, where: str):
    if not path.is_file():
        raise FileNotFoundError(f"{where}: {path} does not exist (paths are relative to the study config)")
    cfg = experiment_from_dict(load_yaml_mapping(path), where=str(path))
    if cfg.stage != stage:
        raise ValueError(f"{where}: {path} is a stage {cfg.stage!r} config; this field takes stage {stage!r}")
    return cfg


def load_rald_ablation(path: str | os.PathLike) -> tuple[RaldAblationConfig, list[ArmPlan]]:
    """Read a study YAML strictly and every config its arms name (relative to the file).

    Raises
    ------
    ValueError
        Unknown fields, bad values, an arm's config of the wrong stage, a diffusion model whose
        latents are not its autoencoder's.
    FileNotFoundError
        A config an arm names is missing.
    """
    from radarpc.config import load_yaml

    path = Path(path)
    cfg = from_dict(RaldAblationConfig, load_yaml_mapping(path), where=str(path))
    base = path.parent
    plans = []
    for i, arm in enumerate(cfg.arms):
        where = f"{path}: arm {arm.name!r}"
        ae = _read_experiment(base / arm.autoencoder, "autoencoder", f"{where}.autoencoder")
        dit = None if arm.diffusion is None else _read_experiment(base / arm.diffusion, "diffusion",
                                                                  f"{where}.diffusion")
        if arm.generate is None:
            gen = GenerateConfig()
        else:
            if not (base / arm.generate).is_file():
                raise FileNotFoundError(f"{where}.generate: {base / arm.generate} does not exist (paths are "
                                        f"relative to the study config)")
            gen = load_yaml(GenerateConfig, base / arm.generate)
        a = ae.model.config
        if dit is not None and (a.n_latents, a.latent_dim) != (dit.model.config.n_latents, dit.model.config.latent_dim):
            raise ValueError(f"{where}: {arm.diffusion} generates {dit.model.config.n_latents} latents of "
                             f"{dit.model.config.latent_dim}, but {arm.autoencoder}'s autoencoder makes {a.n_latents} "
                             f"of {a.latent_dim}")
        init = _init_plan(arm, plans, where)
        if init is not None and dit is not None and ae != init.autoencoder:
            raise ValueError(f"{where}: init: {arm.init} trains another autoencoder ({init.arm.autoencoder}); a "
                             f"fine-tuned diffusion model keeps its autoencoder: give the same autoencoder config")
        from_dir = None if init is None else (init.stage2_dir or init.stage1_dir)
        s1 = f"stage1/{ae.name}-{_digest(to_dict(ae))}"
        if dit is None and init is not None:
            s1 = f"stage1/{ae.name}-{_digest({'experiment': to_dict(ae), 'init': from_dir})}"
        s2 = None
        if dit is not None:
            what = {"experiment": to_dict(dit), "ae": s1} | ({"init": from_dir} if init else {})
            s2 = f"stage2/{dit.name}-{_digest(what)}"
        plans.append(ArmPlan(arm, i, ae, dit, gen, s1, s2, init))
        _check_init_model(plans[-1], where)
    return cfg, plans


def _init_plan(arm: RaldArm, plans: list[ArmPlan], where: str) -> ArmPlan | None:
    if arm.init is None:
        return None
    init = next((p for p in plans if p.arm.name == arm.init), None)
    if init is None:
        raise ValueError(f"{where}: init: {arm.init!r} is not an earlier arm of the study (arms before it: "
                         f"{', '.join(p.arm.name for p in plans) or 'none'})")
    if (arm.diffusion is None) != (init.diffusion is None):
        mine = "stage 1" if arm.diffusion is None else "stage 2"
        its = "stage 1" if init.diffusion is None else "stage 2"
        raise ValueError(f"{where}: init: {arm.init!r} ends with its {its}, this arm with its {mine}; a fine-tuning "
                         f"starts from the same stage")
    return init


def _check_init_model(plan: ArmPlan, where: str) -> None:
    if plan.init is None:
        return
    mine = plan.diffusion if plan.diffusion is not None else plan.autoencoder
    its = plan.init.diffusion if plan.init.diffusion is not None else plan.init.autoencoder
    if to_dict(mine.model) != to_dict(its.model):
        raise ValueError(f"{where}: init: {plan.init.arm.name!r} trains model {its.model.variant!r} with overrides "
                         f"{its.model.overrides or {}}, this arm {mine.model.variant!r} with "
                         f"{mine.model.overrides or {}}; "
                         f"a fine-tuning starts from the same network")


def arm_key(cfg: RaldAblationConfig, plan: ArmPlan) -> dict:
    """What makes an arm's row this arm's: the resolved configs, the data (the root's folder name,
    so a row is the same on every machine), split, ``every`` and the EMD subset size."""
    key = {"autoencoder": to_dict(plan.autoencoder),
           "diffusion": None if plan.diffusion is None else to_dict(plan.diffusion),
           "generate": to_dict(plan.generate),
           "data": Path(cfg.data).name, "split": cfg.split, "every": cfg.every, "emd_points": cfg.emd_points}
    if plan.init is not None:                # what the fine-tuning started from: that arm's configs and its own start
        init = arm_key(cfg, plan.init)
        key["init"] = {"arm": plan.init.arm.name, **{k: init.get(k) for k in ("autoencoder", "diffusion", "init")}}
    return plain_json(key)


def _canonical_arm_key(key: object) -> object:
    """A stored row key with its configs read through today's config types, so that a field added
    since the row was written compares as its default (chained ``init`` keys too)."""
    if not isinstance(key, dict):
        return key
    out = dict(key)
    for k in ("autoencoder", "diffusion"):
        if isinstance(key.get(k), dict):
            try:
                out[k] = to_dict(experiment_from_dict(key[k], where=k))
            except ValueError:
                pass                            # unreadable: compared as stored, and refused as different
    if isinstance(key.get("init"), dict):
        out["init"] = _canonical_arm_key(key["init"])
    return plain_json(out)


def run_rald_ablation(path: str | os.PathLike, out: str | os.PathLike, *, data: str | os.PathLike | None = None,
                      stages: str | os.PathLike | None = None, device: str | None = None, progress: bool = True,
                      log: Callable[[str], None] = print, command: str | None = None) -> dict[str, Path]:
    """Run the study ``path`` into ``out`` (module docstring); returns the rows' paths by arm.

    ``data`` replaces the config's root (its folder name must be the same: rows name it).
    ``stages``: the folder of the stage runs (``stage1/``, ``stage2/``) in place of ``out``, so that
    studies sharing an arm's configs share its trained runs (``radarpc experiment rald-ablation
    --cache``); predictions and rows stay in ``out``.

    Raises
    ------
    ValueError
        A row of an arm holds another key (the fields named), or anything the configs refuse.
    """
    from radarpc.pipelines.point_eval import evaluate_folders
    from radarpc.training.checkpoint import software_record
    from radarpc.training.loop import training_status

    cfg, plans = load_rald_ablation(path)
    root = Path(cfg.data if data is None else data)
    if data is not None and Path(data).name != Path(cfg.data).name:
        raise ValueError(f"--data {data}: the study's rows name the root {Path(cfg.data).name!r} (its folder name); "
                         f"give a copy of that root, or change data: in {path}")
    out = Path(out)
    base = out if stages is None else Path(stages)       # where the stage runs live
    rows = read_rows(out, row_format=RALD_ROW_FORMAT, required=RALD_ROW_FIELDS)
    done: dict[str, Path] = {}
    for plan in plans:
        name, key = plan.arm.name, arm_key(cfg, plan)
        row = rows.get(name)
        if row is not None:
            diff = flat_differences(_canonical_arm_key(row["key"]), key)
            if diff:
                more = f" (and {len(diff) - 3} more)" if len(diff) > 3 else ""
                raise ValueError(f"{out / RESULTS_DIR / (name + '.json')}: made by another configuration of arm "
                                 f"{name!r}: {'; '.join(diff[:3])}{more}. Remove the row (and {out / plan.preds_dir}) "
                                 f"to run the arm again with this config, or give another --out")
            log(f"[{plan.order + 1}/{len(plans)}] {name}: finished (its row is present), reused")
            done[name] = out / RESULTS_DIR / f"{name}.json"
            continue
        init = None if plan.init is None else base / (plan.init.stage2_dir or plan.init.stage1_dir)
        log(f"[{plan.order + 1}/{len(plans)}] {name}: stage 1 in {base / plan.stage1_dir}")
        fits = {"stage1": train_autoencoder(plan.autoencoder, root, base / plan.stage1_dir, device=device,
                                            progress=progress, log=log, init=init if plan.diffusion is None else None),
                "stage2": None}
        run_dir = base / plan.stage1_dir
        if plan.diffusion is not None:
            log(f"[{plan.order + 1}/{len(plans)}] {name}: stage 2 in {base / plan.stage2_dir}")
            fits["stage2"] = train_diffusion(plan.diffusion, root, run_dir, base / plan.stage2_dir, device=device,
                                             progress=progress, log=log, init=init)
            run_dir = base / plan.stage2_dir
        preds = out / plan.preds_dir
        log(f"[{plan.order + 1}/{len(plans)}] {name}: {'generating' if plan.diffusion else 'reconstructing'} "
            f"split {cfg.split!r} into {preds}")
        generate_run(run_dir, preds, data=root, split=cfg.split, every=cfg.every, config=plan.generate,
                     device=device, progress=progress, notice=log)
        evaluation = evaluate_folders([preds], root, cfg.split, emd_points=cfg.emd_points, progress=progress)
        report = next(iter(evaluation.reports.values()))
        status = {"stage1": training_status(base / plan.stage1_dir),
                  "stage2": None if plan.stage2_dir is None else training_status(base / plan.stage2_dir)}
        row = {"format": RALD_ROW_FORMAT, "run": name,
               "study": {"name": cfg.name, "kind": "rald-ablation", "config_file": str(path), "config": to_dict(cfg)},
               "arm": {"name": name, "label": plan.label, "order": plan.order,
                       "output": "generation" if plan.diffusion else "reconstruction",
                       "autoencoder": plan.arm.autoencoder, "diffusion": plan.arm.diffusion,
                       "generate": plan.arm.generate, "init": plan.arm.init,
                       "scenes": {"stage1": _scenes(plan.autoencoder),
                                  "stage2": None if plan.diffusion is None else _scenes(plan.diffusion)}},
               "key": key,
               "metrics": {"overall": asdict(report.overall), "scenes": [asdict(s) for s in report.scenes]},
               "runs": status, "validation": {k: None if f is None else f.best_row for k, f in fits.items()},
               "evaluation": {"split": cfg.split, "every": cfg.every, "emd_points": cfg.emd_points},
               "command": command, "software": software_record(),
               "times": {"finished_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}}
        done[name] = write_named_row(out, f"{name}.json", row)
        log(f"[{plan.order + 1}/{len(plans)}] {name}: CD {_num(report.overall.chamfer_mean)} m, "
            f"EMD {_num(report.overall.emd_mean)} m over {report.overall.n_scored} frames; row {done[name]}")
    return done


def _num(x, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _scenes(cfg) -> list[str] | None:
    return None if cfg.scenes is None else list(cfg.scenes)


def _trained_on(arm: dict) -> str:
    """``hallway, classroom / lab`` (stage 1 / stage 2 scenes; ``all``: every scene), and the arm it
    fine-tunes."""
    sc = arm.get("scenes") or {}
    stages = ("stage1", "stage2") if arm.get("output") == "generation" else ("stage1",)
    text = " / ".join("all" if sc.get(k) is None else ", ".join(sc[k]) for k in stages)
    return text + (f" (from `{arm['init']}`)" if arm.get("init") else "")


def write_rald_report(runs: str | os.PathLike, out: str | os.PathLike | None = None, *, command: str | None = None,
                      log: Callable[[str], None] = print) -> Path:
    """Write ``report.md`` of a RaLD ablation's rows (default into ``RUNS/report``): a Table-3-like
    table, one row per arm in the study's order, CD and EMD (means, metres) per scene and over all
    frames, then every arm's frames, empty predictions, steps, validation at the best weights and commit.

    Raises
    ------
    FileNotFoundError
        No result row in ``runs``.
    """
    runs = Path(runs)
    rows = read_rows(runs, row_format=RALD_ROW_FORMAT, required=RALD_ROW_FIELDS)
    if not rows:
        raise FileNotFoundError(f"{runs}: no result rows (no {RESULTS_DIR}/*.json); run `radarpc experiment "
                                f"rald-ablation ...` first, or give the study's output folder")
    base = runs.parent if runs.name == RESULTS_DIR and not (runs / RESULTS_DIR).is_dir() else runs
    out = Path(out) if out is not None else base / "report"
    made = provenance(rows, base / RESULTS_DIR, runs, command)
    ordered = sorted(rows.values(), key=lambda r: (int(r["arm"].get("order", 10**6)), r["run"]))
    scenes = sorted({s["scene"] for r in ordered for s in r["metrics"]["scenes"]})
    splits = sorted({str((r.get("evaluation") or {}).get("split", "?")) for r in ordered})
    head = ["arm"] + [f"{s} {m}" for s in [*scenes, "all"] for m in ("CD↓", "EMD↓")]
    lines = made.header(f"RaLD ablation {', '.join(made.studies)}", "trained, generated and scored the arms") + [
        f"CD (RaLD's non-squared Chamfer distance) and EMD (Wasserstein-1 between uniform subsets) in metres, "
        f"the means over each scene's scored frames of the {'/'.join(splits)} split (`radarpc evaluate-points`); "
        f"arms in the study's order.", "",
        "| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for r in ordered:
        by_scene = {s["scene"]: s for s in r["metrics"]["scenes"]}
        cells = [r["arm"].get("label") or r["run"]]
        for s in [*scenes, "all"]:
            m = r["metrics"]["overall"] if s == "all" else by_scene.get(s)
            cells += ["-", "-"] if m is None else [_num(m.get("chamfer_mean")), _num(m.get("emd_mean"))]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "### arms", "", "Trained on: the scenes of stage 1 / stage 2 (all: every scene of the root's "
              "training runs; the others are held out), and the arm a fine-tuning started from.", "",
              "Validation at the best weights (`log.csv` of the stage runs): stage 1's loss; stage 2's EDM loss "
              "and its radar check, how much the frame's own radar lowers that loss against another run's "
              "(`val_radar_gain`; 0: the model ignores the radar; `-`: a row written before the rows held it).", "",
              "| arm | output | trained on | frames | empty | stage-1 steps | stage-2 steps | stage-1 val loss | "
              "stage-2 val loss | radar check | commit |",
              "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in ordered:
        o, st, val = r["metrics"]["overall"], r.get("runs") or {}, r.get("validation") or {}
        steps = [(st.get(k) or {}).get("steps_done", "-") if st.get(k) else "-" for k in ("stage1", "stage2")]
        v1, v2 = val.get("stage1") or {}, val.get("stage2") or {}
        commit = (r.get("software") or {}).get("commit") or "-"
        lines.append(f"| `{r['run']}` | {r['arm'].get('output', '-')} | {_trained_on(r['arm'])} | {o['n_frames']} | "
                     f"{o.get('empty', 0)} | {steps[0]} | {steps[1]} | {_num(v1.get('val_loss'))} | "
                     f"{_num(v2.get('val_loss'))} | {_num(v2.get('val_radar_gain'), 4)} | `{commit[:10]}` |")
    lines += [""] + made.config_section()
    path = out / RALD_REPORT_MD
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    log(f"wrote {path}")
    return path
