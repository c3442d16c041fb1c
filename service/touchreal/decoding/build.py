"""``decoders train`` end to end: encode, fit, export, evaluate through onnxruntime, write.

Each model is fitted on the training split of its protocol, exported, reloaded through the
validating loader and evaluated by onnxruntime on the held-out split; its metrics go into its
metadata before the files are written (``<name>.onnx`` + ``<name>.json``, sweeps under ``sweep/``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..params import EncoderParams
from ..recording import Dataset
from .evaluate import TrialCache, evaluate_model, flat_metrics, protocol_of
from .export import set_metadata
from .model import DecoderModel, load_model, write_model
from .plan import ModelSpec
from .train import train_model


def train_all(
    ds: Dataset,
    params: EncoderParams,
    specs: Sequence[ModelSpec],
    out_dir: str | Path,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    cache: TrialCache | None = None,
) -> dict[str, Any]:
    """Train, export and write every spec; return the flat held-out metrics of all of them."""
    out_dir = Path(out_dir)
    cache = cache or TrialCache(ds, params)
    flat: dict[str, Any] = {}
    for spec in specs:
        train = cache.trials(spec, "train")
        held = cache.trials(spec, "heldout")
        # the folder's name only: the metadata travels with the model to every client (no build-machine paths)
        training = {"dataset": str(ds.manifest.get("name", ds.root.name)), "dataset_dir": ds.root.name,
                    "protocol": protocol_of(spec.task), "split": "train", "split_seed": cache.split_seed,
                    "heldout_trials": len(held), "seed": seed}
        model, meta, _, _ = train_model(spec, train, params, training, seed)
        dm = DecoderModel(Path(f"{spec.name}.onnx"), meta, model.SerializeToString())
        metrics = evaluate_model(dm, held) if held else {}
        meta["metrics"] = metrics | {"evaluated_on": f"{len(held)} held-out {protocol_of(spec.task)} trials (onnxruntime)"} if held \
            else {"evaluated_on": "nothing: the split held out no trial"}
        set_metadata(model, meta)
        path = write_model(out_dir / spec.folder, model, meta)
        load_model(path)  # what was written loads and validates
        if held:
            flat.update(flat_metrics(spec, metrics))
        if progress is not None:
            progress(spec.name)
    return flat
