"""``touchreal decoders {train,evaluate,list}``: thin I/O around :mod:`touchreal.decoding`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ..decoding.plan import TASKS


def _tasks(text: str) -> tuple[str, ...]:
    tasks = tuple(t.strip() for t in text.split(",") if t.strip())
    bad = [t for t in tasks if t not in TASKS]
    if bad or not tasks:
        raise argparse.ArgumentTypeError(f"tasks are a comma-separated subset of {','.join(TASKS)}")
    return tasks


def _names(text: str) -> tuple[str, ...]:
    names = tuple(t.strip() for t in text.split(",") if t.strip())
    if not names:
        raise argparse.ArgumentTypeError("--only takes comma-separated model names")
    return names


def _windows(text: str) -> tuple[float, ...]:
    try:
        ws = tuple(float(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected windows in ms like 100,200,500; got {text!r}") from None
    if not ws or min(ws) <= 0:
        raise argparse.ArgumentTypeError("windows must be > 0 ms")
    return ws


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("decoders", help="train, evaluate and list the spike decoders (force, texture; ONNX)",
                       description="Downstream decoders on TouchReal spikes: force regression from SA1/RA and "
                       "texture classification from PC, exported to ONNX (docs/decoders.md).")
    cmds = p.add_subparsers(dest="decoders_command", required=True, metavar="SUBCOMMAND")

    t = cmds.add_parser("train", help="train the decoders on a dataset and write ONNX models + metadata")
    t.add_argument("dataset", help="dataset folder (ramp trials for force, texture trials for texture)")
    t.add_argument("--params", help="encoder parameter file (default: the shipped parameters)")
    t.add_argument("--out", required=True, help="models folder to write (<name>.onnx + <name>.json, sweeps in sweep/)")
    t.add_argument("--tasks", type=_tasks, default=TASKS, help="force,texture (default both)")
    t.add_argument("--no-sweeps", action="store_true", help="only the product models (no window sweeps)")
    t.add_argument("--only", type=_names, help="only these models of the plan (comma-separated names, e.g. "
                   "texture_spectral,texture_spectral_w100ms)")
    t.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=run_train)

    e = cmds.add_parser("evaluate", help="run ONNX decoders through onnxruntime on a dataset; write METRICS.json")
    e.add_argument("dataset", help="dataset folder")
    e.add_argument("--params", help="encoder parameter file (default: the shipped parameters)")
    e.add_argument("--models", help="models folder (default: the installed models)")
    e.add_argument("--out", required=True, help="METRICS.json to write")
    e.add_argument("--split", choices=("heldout", "all", "train"), default="heldout",
                   help="trials to evaluate on: the held-out split (default), all (a test-only dataset) or train")
    e.add_argument("--tasks", type=_tasks, default=TASKS, help="force,texture (default both)")
    e.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads (default 1)")
    e.add_argument("--quiet", action="store_true", help="no progress bar")
    e.set_defaults(func=run_evaluate)

    c = cmds.add_parser("ceiling", help="the raw-PVDF ceiling of the scanning texture task: the film's spectrum on the "
                        "spatial model's windows, same split and classifier")
    c.add_argument("dataset", help="dataset folder with texture trials (trains on its training split)")
    c.add_argument("--test", help="test dataset (all its trials; default: the dataset's held-out split)")
    c.add_argument("--params", help="encoder parameter file (default: the shipped parameters; they only set the split seed)")
    c.add_argument("--windows", type=_windows, default=(100.0, 200.0, 500.0), help="windows in ms (default 100,200,500)")
    c.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    c.add_argument("--out", required=True, help="JSON to write (texture.pvdf_ceiling.acc_<w>ms, ...)")
    c.set_defaults(func=run_ceiling)

    ls = cmds.add_parser("list", help="list the installed decoder models")
    ls.add_argument("--user-dir", help="user models folder (default: none, shipped models only)")
    ls.set_defaults(func=run_list)


def _params(path: str | None):
    from ..params import EncoderParams, default_params

    return default_params() if path is None else EncoderParams.load(path)


def _bar(total: int, quiet: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", disable=quiet, file=sys.stderr)


def run_train(args: argparse.Namespace) -> int:
    from ..recording import Dataset
    from ..decoding.build import train_all
    from ..decoding.evaluate import TrialCache
    from ..decoding.plan import plan
    from ..decoding.windows import require_trials

    ds = Dataset.open(args.dataset)
    params = _params(args.params)
    for task in args.tasks:
        require_trials(ds, "ramp" if task == "force" else "texture", f"the {task} decoder")
    specs = plan(args.tasks, sweeps=not args.no_sweeps)
    if args.only:
        unknown = sorted(set(args.only) - {s.name for s in specs})
        if unknown:
            raise ValueError(f"--only: {unknown} are not in the plan for tasks {','.join(args.tasks)} "
                             f"(models: {', '.join(s.name for s in specs)})")
        specs = [s for s in specs if s.name in args.only]
    cache = TrialCache(ds, params)
    total = cache.n_to_encode(specs, "all") + len(specs)
    with _bar(total, args.quiet, "decoders train") as bar:
        cache.progress = lambda: bar.update(1)
        metrics = train_all(ds, params, specs, args.out, args.seed, progress=lambda name: (bar.set_postfix_str(name), bar.update(1)), cache=cache)
    out = Path(args.out) / "metrics.json"
    out.write_text(json.dumps(_with_info(metrics, ds, "heldout", cache.split_seed, params), indent=1, sort_keys=True) + "\n")
    print(f"wrote {len(specs)} models to {args.out} (held-out metrics in {out})")
    _summary(metrics)
    return 0


def _load_models(folder: str | None, tasks: tuple[str, ...]):
    from ..decoding.model import ModelStore, load_model

    if folder is None:
        store = ModelStore()
        models = [store.load(m["name"]) for m in store.list()]
    else:
        root = Path(folder)
        if not root.is_dir():
            raise ValueError(f"{root}: no such models folder")
        models = [load_model(p) for p in sorted(root.glob("*.onnx")) + sorted((root / "sweep").glob("*.onnx"))]
    models = [m for m in models if m.meta["task"] in tasks]
    if not models:
        raise ValueError(f"{folder or 'installed models'}: no decoder model for tasks {','.join(tasks)}")
    return models


def run_evaluate(args: argparse.Namespace) -> int:
    from ..recording import Dataset, RecordingError
    from ..decoding.evaluate import TrialCache, evaluate_models, protocol_of
    from ..decoding.model import params_warning
    from ..decoding.plan import spec_from_meta
    from ..decoding.windows import require_trials, split_entries

    ds = Dataset.open(args.dataset)
    params = _params(args.params)
    models = _load_models(args.models, args.tasks)
    tasks = sorted({m.meta["task"] for m in models})
    for task in tasks:  # a task with no trials at all is the clearer error: before any split is looked at
        require_trials(ds, protocol_of(task), f"evaluating the {task} decoders")
    for task in tasks:
        if not split_entries(ds, params, protocol_of(task), args.split)[0]:
            raise RecordingError(f"{ds.root}: no {protocol_of(task)} trials in the {args.split} split, nothing to "
                                 f"evaluate the {task} decoders on (a test-only dataset: --split all)")
    warnings = [w for w in (params_warning(m.meta, params) for m in models) if w]
    for w in warnings[:3]:
        print(f"warning: {w}", file=sys.stderr)
    cache = TrialCache(ds, params)
    _check_split(models, ds, args.split, cache)
    total = cache.n_to_encode([spec_from_meta(m.meta) for m in models], args.split) + len(models)
    with _bar(total, args.quiet, "decoders evaluate") as bar:
        cache.progress = lambda: bar.update(1)
        metrics = evaluate_models(models, cache, args.split, args.threads, done=lambda name: (bar.set_postfix_str(name), bar.update(1)))
    report = _with_info(metrics, ds, args.split, cache.split_seed, params)
    report["info.params_warnings"] = warnings
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=1, sort_keys=True) + "\n")
    print(f"evaluated {len(models)} models on the {args.split} trials of {ds.root}; wrote {args.out}")
    _summary(metrics)
    return 0


def _check_split(models, ds, split: str, cache) -> None:
    """A held-out evaluation on the training dataset must use the split the models were trained with."""
    from ..decoding.windows import split_entries

    if split == "all":
        return
    name = str(ds.manifest.get("name", ds.root.name))
    for m in models:
        tr = m.meta["training"]
        if tr.get("dataset") == name:
            _, seed = split_entries(ds, cache.params, tr["protocol"], split)
            if tr.get("split_seed") != seed:
                raise ValueError(f"{m.name} was trained on {name} with split seed {tr.get('split_seed')}, these parameters "
                                 f"give seed {seed}: its held-out trials would overlap its training trials")


def _with_info(metrics: dict[str, Any], ds, split: str, seed: int | None, params) -> dict[str, Any]:
    from ..decoding.model import params_hash

    return {**metrics, "info.dataset": str(ds.manifest.get("name", ds.root.name)), "info.dataset_dir": str(ds.root),
            "info.split": split, "info.split_seed": seed, "info.params_sha256": params_hash(params), "info.runtime": "onnxruntime"}


def _summary(metrics: dict[str, Any]) -> None:
    for k in sorted(metrics):
        if k.startswith("force.") and ".window." not in k and k.rsplit(".", 1)[1] in ("rmse", "r2", "pearson_r", "oscillation"):
            print(f"  {k} = {metrics[k]:.4f}")
        elif k.startswith("texture.") and k.rsplit("_", 1)[-1] == "500ms" and "prewindow" not in k:
            print(f"  {k} = {metrics[k]:.3f}")


def run_ceiling(args: argparse.Namespace) -> int:
    from ..decoding.ceiling import ceiling
    from ..decoding.plan import SPECTRAL_BIN_MS, SPECTRAL_CLASSES, ModelSpec
    from ..decoding.windows import TEXTURE_PROTOCOL, encode, require_trials, split_entries
    from ..recording import Dataset

    ds = Dataset.open(args.dataset)
    params = _params(args.params)
    require_trials(ds, TEXTURE_PROTOCOL, "the PVDF ceiling")
    test_ds = Dataset.open(args.test) if args.test else ds
    if args.test:
        require_trials(test_ds, TEXTURE_PROTOCOL, "the PVDF ceiling")

    def load(d, split):
        entries = split_entries(d, params, TEXTURE_PROTOCOL, split)[0]
        raw = [d.load(e) for e in entries]
        return [encode(e, r, params) for e, r in zip(entries, raw)], raw

    train, train_raw = load(ds, "train")
    test, test_raw = load(test_ds, "all" if args.test else "heldout")
    out: dict[str, Any] = {}
    for w in args.windows:
        spec = ModelSpec(f"pvdf_ceiling_w{w:g}ms", "texture", SPECTRAL_CLASSES, w, "spatial", bin_ms=SPECTRAL_BIN_MS)
        m = ceiling(spec, train, train_raw, test, test_raw, args.seed)
        head = f"texture.pvdf_ceiling.acc_{w:g}ms"
        out.update({head: m["acc"], f"{head}_fold_std": m["acc_fold_std"], f"{head}_windows": m["n_windows"]})
        print(f"  {head} = {m['acc']:.3f} ± {m['acc_fold_std']:.3f} ({m['n_windows']} windows)")
    out |= {"info.dataset": str(ds.root), "info.test": str(test_ds.root) if args.test else "heldout", "info.runtime": "scikit-learn"}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    return 0


def run_list(args: argparse.Namespace) -> int:
    from ..decoding.model import ModelStore

    for m in ModelStore(args.user_dir).list():
        if "error" in m:
            print(f"{m['name']:<24} {m['source']:<8} ERROR {m['error']}")
        else:
            print(f"{m['name']:<24} {m['source']:<8} {m['task']:<8} {'+'.join(m['classes']):<7} {m['window_ms']:>6g} ms  {m['description']}")
    return 0
