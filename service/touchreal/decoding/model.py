"""Decoder model files: metadata, validated loading, onnxruntime sessions and the model store.

A decoder is one ONNX file ``<name>.onnx``; its metadata (JSON, format in docs/decoders.md) is
embedded in the file's ``metadata_props`` under ``touchreal.decoder`` and written next to it as
``<name>.json`` for listing. Loading checks that the file is ONNX, that the metadata is complete,
that the sidecar (when present) equals the embedded copy, and that the graph's input and outputs
are those the metadata describes; every failure is a :class:`DecoderModelError` naming the file.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from touchreal_client import features as F

from ..params import EncoderParams, PreprocessParams
from ..settings import PACKAGE_DATA
from .export import META_KEY
from .features import SPEED_INPUT
from .state import step_index

SCHEMA = "touchreal.decoder"
SCHEMA_VERSION = 1
TASKS = ("force", "texture")
SHIPPED_MODELS = PACKAGE_DATA / "models"
_REQUIRED = ("schema", "version", "name", "task", "input", "outputs", "output_names", "classes", "bin_ms", "window_ms",
             "step_ms", "alignment", "features", "params", "training", "metrics")


class DecoderModelError(ValueError):
    """A decoder model file or its metadata is unusable."""


def params_hash(params: EncoderParams) -> str:
    """sha256 of the parameter values (provenance excluded: it describes, it does not change spikes;
    so is a class's absent high-pass, a field of version 4, and the default mains candidates, a later
    field, so that a set hashes as it did before them)."""
    data = params.model_dump(mode="json", by_alias=True, exclude={"provenance"})
    for c in data["classes"].values():
        if c.get("highpass_hz") is None:
            c.pop("highpass_hz", None)
    if data["preprocess"].get("mains_candidates_hz") == PreprocessParams().mains_candidates_hz:
        data["preprocess"].pop("mains_candidates_hz")
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def with_pvdf_window(params: EncoderParams, window_ms: float | None) -> EncoderParams:
    """``params`` with the causal PVDF window set to ``window_ms`` for every class (the
    preprocessing default and any class's own window), or unchanged for None."""
    if window_ms is None:
        return params
    pre = params.preprocess.model_copy(update={"window_ms": float(window_ms)})
    classes = {c: p if p.window_ms is None else p.model_copy(update={"window_ms": float(window_ms)}) for c, p in params.classes.items()}
    return params.model_copy(update={"preprocess": pre, "classes": classes})


def params_warning(meta: dict[str, Any], params: EncoderParams) -> str | None:
    """A warning when ``params`` (the active set) differ from those the model was trained on, else None."""
    want = meta["params"]["sha256"]
    have = params_hash(with_pvdf_window(params, meta["params"].get("pvdf_window_ms")))
    if have == want:
        return None
    return (f"decoder {meta['name']!r} was trained on parameters {want[:12]} ({meta['params'].get('source', '?')}); "
            f"the active parameters are {have[:12]}: its outputs may be off")


def validate_metadata(meta: Any, where: str) -> dict[str, Any]:
    """Check the metadata's structure; return it."""
    if not isinstance(meta, dict):
        raise DecoderModelError(f"{where}: metadata must be a JSON object")
    missing = [k for k in _REQUIRED if k not in meta]
    if missing:
        raise DecoderModelError(f"{where}: metadata lacks {missing}")
    if meta["schema"] != SCHEMA or meta["version"] != SCHEMA_VERSION:
        raise DecoderModelError(f"{where}: metadata schema {meta['schema']!r} v{meta['version']}, expected {SCHEMA!r} v{SCHEMA_VERSION}")
    if meta["task"] not in TASKS:
        raise DecoderModelError(f"{where}: unknown task {meta['task']!r}")
    if any(c not in F.CLASSES for c in meta["classes"]) or not meta["classes"]:
        raise DecoderModelError(f"{where}: classes {meta['classes']!r} are not a subset of {list(F.CLASSES)}")
    nb = F.n_bins(round(meta["window_ms"] * 1000), round(meta["bin_ms"] * 1000))
    if meta["input"].get("shape") != [None, nb, len(meta["classes"])]:
        raise DecoderModelError(f"{where}: metadata input shape {meta['input'].get('shape')} does not match "
                                f"window {meta['window_ms']} ms / bin {meta['bin_ms']} ms x {len(meta['classes'])} classes")
    align = meta["alignment"]
    if align is not None and (align.get("rule") != F.ALIGN_RULE or align.get("class") not in meta["classes"]):
        raise DecoderModelError(f"{where}: unknown alignment {align!r}")
    if meta["task"] == "texture" and (not meta.get("labels") or meta["output_names"] != meta["labels"]):
        raise DecoderModelError(f"{where}: a texture model names its labels (output_names == labels)")
    context = meta.get("context")
    if context is not None and (not isinstance(context, dict) or context.get("input") != SPEED_INPUT
                                or context.get("shape") != [None, 1] or context.get("unit") != "mm/s"):
        raise DecoderModelError(f"{where}: the one context input is {{'input': {SPEED_INPUT!r}, 'shape': [null, 1], "
                                f"'unit': 'mm/s'}}; got {context!r}")
    state = meta.get("state")
    if state is not None:
        ok = (isinstance(state, dict) and isinstance(state.get("size"), int) and state["size"] > 0
              and isinstance(state.get("input"), str) and isinstance(meta["outputs"], list)
              and state.get("output") in meta["outputs"][1:]
              and meta["window_ms"] == meta["step_ms"])
        if not ok:
            raise DecoderModelError(f"{where}: a stateful model names its state input, its state output (after the "
                                    f"first output) and size, and its window equals its step; got {state!r}")
    return meta


def _graph_shape(vi: onnx.ValueInfoProto) -> list[int | None]:
    return [d.dim_value if d.HasField("dim_value") else None for d in vi.type.tensor_type.shape.dim]


@dataclass
class DecoderModel:
    """A validated decoder: the ONNX bytes (what clients download) and the metadata."""

    path: Path
    meta: dict[str, Any]
    onnx_bytes: bytes

    @property
    def name(self) -> str:
        return str(self.meta["name"])

    @property
    def window_us(self) -> int:
        return round(self.meta["window_ms"] * 1000)

    @property
    def bin_us(self) -> int:
        return round(self.meta["bin_ms"] * 1000)

    @property
    def step_us(self) -> int:
        return round(self.meta["step_ms"] * 1000)

    def session(self, threads: int = 1):
        """An onnxruntime CPU session with explicit thread counts (``threads`` intra-op, 1 inter-op)."""
        import onnxruntime as ort

        if threads < 1:
            raise ValueError("threads must be >= 1")
        so = ort.SessionOptions()
        so.intra_op_num_threads = int(threads)
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        return ort.InferenceSession(self.onnx_bytes, so, providers=["CPUExecutionProvider"])

    @property
    def needs_speed(self) -> bool:
        """True when the graph reads the scanning speed (metadata ``context``, input ``speed_mm_s``)."""
        return self.meta.get("context") is not None

    @property
    def stateful(self) -> bool:
        """True when the graph carries state across steps (metadata ``state``)."""
        return self.meta.get("state") is not None

    def initial_state(self, batch: int) -> np.ndarray:
        """The state before the first step: zeros ``(batch, size)`` float32 (``(batch, 0)`` stateless)."""
        return np.zeros((batch, self.meta["state"]["size"] if self.stateful else 0), np.float32)

    def run(self, session, counts: np.ndarray, state: np.ndarray | None = None,
            speed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """One step: ((batch, n_outputs) float32 force (N) or label probabilities, the next state or
        None) from a counts tensor and, for a stateful model, the previous state (required; a
        stateless model ignores it); a model with a speed context needs ``speed`` (mm/s, (batch, 1)
        or (1, 1)), others ignore it."""
        feeds = {self.meta["input"]["name"]: np.asarray(counts, np.float32)}
        if self.needs_speed:
            if speed is None:
                raise ValueError(f"{self.name} reads the scanning speed: pass speed (mm/s)")
            feeds[SPEED_INPUT] = np.asarray(speed, np.float32).reshape(-1, 1)
        if not self.stateful:
            return session.run([self.meta["outputs"][0]], feeds)[0], None
        if state is None:
            raise ValueError(f"{self.name} is stateful: pass its state (initial_state at the first step)")
        feeds[self.meta["state"]["input"]] = np.asarray(state, np.float32)
        out, nxt = session.run([self.meta["outputs"][0], self.meta["state"]["output"]], feeds)
        return out, nxt

    def run_windows(self, session, counts: np.ndarray, groups: np.ndarray, speed: np.ndarray | None = None,
                    chunk: int = 1024) -> np.ndarray:
        """(n, n_outputs) for the windows of recorded trials (``groups``: trial of each row, a trial's
        windows contiguous and consecutive steps; ``speed`` (n, 1) mm/s for a model that reads it).
        A stateless model runs ``chunk`` rows per call; a stateful one one step of every trial per
        call, each trial's state from zero, as a stream of it would."""
        if not self.stateful:
            out = np.zeros((counts.shape[0], len(self.meta["output_names"])), np.float32)
            for a in range(0, counts.shape[0], chunk):
                rows = slice(a, a + chunk)
                out[rows] = self.run(session, counts[rows], None, None if speed is None else speed[rows])[0]
            return out
        pos = step_index(groups)
        out = np.zeros((pos.size, len(self.meta["output_names"])), np.float32)
        state = self.initial_state(pos.size)
        for k in range(int(pos.max()) + 1 if pos.size else 0):
            rows = np.flatnonzero(pos == k)
            prev = state[rows - 1] if k else self.initial_state(rows.size)
            out[rows], state[rows] = self.run(session, counts[rows], prev)
        return out


def read_onnx_metadata(model: onnx.ModelProto, where: str) -> dict[str, Any]:
    props = {p.key: p.value for p in model.metadata_props}
    if META_KEY not in props:
        raise DecoderModelError(f"{where}: ONNX model without TouchReal decoder metadata ({META_KEY!r})")
    try:
        return json.loads(props[META_KEY])
    except json.JSONDecodeError as exc:
        raise DecoderModelError(f"{where}: embedded metadata is not JSON ({exc})") from exc


def load_model(path: str | Path) -> DecoderModel:
    """Read and validate ``path`` (``.onnx``) and its sidecar ``.json`` if present."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DecoderModelError(f"{path}: cannot read ({exc})") from exc
    try:
        model = onnx.load_model_from_string(data)
        onnx.checker.check_model(model)
    except Exception as exc:  # protobuf DecodeError, ValidationError: all mean "not a usable ONNX file"
        raise DecoderModelError(f"{path}: not an ONNX model ({type(exc).__name__}: {str(exc)[:200]})") from exc
    meta = validate_metadata(read_onnx_metadata(model, str(path)), str(path))
    sidecar = path.with_suffix(".json")
    if sidecar.is_file():
        try:
            side = json.loads(sidecar.read_text())
        except json.JSONDecodeError as exc:
            raise DecoderModelError(f"{sidecar}: not JSON ({exc})") from exc
        if side != meta:
            diff = sorted(k for k in set(side) | set(meta) if side.get(k) != meta.get(k))
            raise DecoderModelError(f"{sidecar}: metadata does not match the one embedded in {path.name} (keys {diff})")
    inputs = [(i.name, _graph_shape(i)[1:]) for i in model.graph.input if i.name not in {t.name for t in model.graph.initializer}]
    want = [(meta["input"]["name"], meta["input"]["shape"][1:])]
    if meta.get("context") is not None:
        want.append((meta["context"]["input"], meta["context"]["shape"][1:]))
    if meta.get("state") is not None:
        want.append((meta["state"]["input"], [meta["state"]["size"]]))
    if inputs != want:
        raise DecoderModelError(f"{path}: graph inputs {inputs} do not match the metadata's {want}")
    outs = [o.name for o in model.graph.output]
    if outs != meta["outputs"]:
        raise DecoderModelError(f"{path}: graph outputs {outs} do not match the metadata's {meta['outputs']}")
    width = _graph_shape(model.graph.output[0])[1]
    if width != len(meta["output_names"]):
        raise DecoderModelError(f"{path}: first output has {width} columns, metadata names {len(meta['output_names'])}")
    return DecoderModel(path, meta, data)


def write_model(folder: str | Path, model: onnx.ModelProto, meta: dict[str, Any]) -> Path:
    """Write ``<name>.onnx`` and its ``<name>.json`` sidecar; return the ONNX path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{meta['name']}.onnx"
    onnx.save_model(model, path)
    path.with_suffix(".json").write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
    return path


class ModelStore:
    """Installed decoders: the package's shipped folder plus a user folder (same name: user wins)."""

    def __init__(self, user_dir: str | Path | None = None, shipped_dir: str | Path = SHIPPED_MODELS):
        self.shipped_dir = Path(shipped_dir)
        self.user_dir = Path(user_dir) if user_dir is not None else None

    def _files(self) -> dict[str, tuple[str, Path]]:
        found: dict[str, tuple[str, Path]] = {}
        for source, folder in (("shipped", self.shipped_dir), ("user", self.user_dir)):
            if folder is not None and folder.is_dir():
                for p in sorted(folder.glob("*.onnx")):
                    found[p.stem] = (source, p)
        return found

    def list(self) -> list[dict[str, Any]]:
        """Metadata of every model (plus ``source`` and ``file``); an unusable file is listed with
        its ``error`` instead of metadata, so one bad upload does not hide the others."""
        out = []
        for name, (source, path) in sorted(self._files().items()):
            try:
                out.append({**load_model(path).meta, "source": source, "file": str(path)})
            except DecoderModelError as exc:
                out.append({"name": name, "source": source, "file": str(path), "error": str(exc)})
        return out

    def path(self, name: str) -> Path:
        files = self._files()
        if name not in files:
            raise DecoderModelError(f"no decoder model named {name!r} (installed: {sorted(files)})")
        return files[name][1]

    def load(self, name: str) -> DecoderModel:
        return load_model(self.path(name))
