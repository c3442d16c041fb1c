"""scikit-learn decoder -> one ONNX graph ``counts -> outputs`` with the metadata embedded.

The exported graph is the feature graph of :class:`~touchreal.decoding.features.FeatureSpec`
followed by the skl2onnx conversion of the fitted pipeline, so a client feeds binned counts and
nothing else. Outputs:

* regression: ``force_N`` (batch, 1) float32; a stateful model (features with a state filter) also
  takes ``state`` and returns ``state_out`` (batch, size) float32, to feed back at the next step;
* classification: ``probabilities`` (batch, n_labels) float32 (no ZipMap) and ``label`` (batch,)
  int64 = ``argmax(probabilities)``, an index into the metadata's ``labels``. The scikit-learn
  side predicts the same way (:func:`predict_labels`), not with ``SVC.predict``.
"""

from __future__ import annotations

import json
import warnings
from typing import Any

import numpy as np
import onnx
from onnx import compose, helper
from sklearn.pipeline import Pipeline
from skl2onnx import convert_sklearn
from skl2onnx.common.data_types import FloatTensorType
from touchreal_client.features import META_KEY  # the key clients read too

from .features import FeatureSpec
from .state import STATE_OUTPUT

TARGET_OPSET = 17
ML_OPSET = 3
INPUT_NAME = "counts"
REGRESSION_OUTPUT = "force_N"


def predict_labels(pipe: Pipeline, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(probabilities, label index = argmax) of a fitted probabilistic classifier pipeline."""
    proba = pipe.predict_proba(features)
    return proba, np.argmax(proba, axis=1)


def to_onnx(pipe: Pipeline, spec: FeatureSpec, meta: dict[str, Any]) -> onnx.ModelProto:
    """The exported model: features graph + converted pipeline, outputs renamed, metadata embedded."""
    n_feat = len(spec.names())
    classifier = hasattr(pipe, "predict_proba")
    options = {id(pipe.steps[-1][1]): {"zipmap": False}} if classifier else None
    with warnings.catch_warnings():  # the converter reads SVC.probA_, deprecated in scikit-learn 1.9
        warnings.simplefilter("ignore", FutureWarning)
        est = convert_sklearn(
            pipe,
            initial_types=[("features", FloatTensorType([None, n_feat]))],
            options=options,
            target_opset={"": TARGET_OPSET, "ai.onnx.ml": ML_OPSET},
        )
    est = compose.add_prefix(est, "est_")
    # the feature graph's operators as of opset 16 (the spatial set's ScatterElements with reduction 'add'); use the converter's opset
    opset = next(o.version for o in est.opset_import if o.domain in ("", "ai.onnx"))
    feats = spec.graph(opset, est.ir_version, INPUT_NAME, "features")
    feats.opset_import.extend([o for o in est.opset_import if o.domain != ""])
    feats = compose.add_prefix(feats, "feat_", rename_inputs=False)
    state_out = [f"feat_{STATE_OUTPUT}"] if spec.state is not None else []
    out_names = [o.name for o in est.graph.output]
    if classifier:
        proba = next(n for n in out_names if n.endswith("probabilities"))
        merged = compose.merge_models(feats, est, io_map=[("feat_features", "est_features")], outputs=[proba])
        g = merged.graph
        g.node.append(helper.make_node("Identity", [proba], ["probabilities"]))
        g.node.append(helper.make_node("ArgMax", [proba], ["label"], axis=1, keepdims=0))
        del g.output[:]
        g.output.extend(
            [
                helper.make_tensor_value_info("probabilities", onnx.TensorProto.FLOAT, [None, len(meta["labels"])]),
                helper.make_tensor_value_info("label", onnx.TensorProto.INT64, [None]),
            ]
        )
    else:
        merged = compose.merge_models(feats, est, io_map=[("feat_features", "est_features")], outputs=[out_names[0]] + state_out)
        g = merged.graph
        g.node.append(helper.make_node("Identity", [out_names[0]], [REGRESSION_OUTPUT]))
        del g.output[:]
        g.output.extend([helper.make_tensor_value_info(REGRESSION_OUTPUT, onnx.TensorProto.FLOAT, [None, 1])])
        if state_out:
            g.node.append(helper.make_node("Identity", state_out, [STATE_OUTPUT]))
            g.output.append(spec.state.value_info(STATE_OUTPUT))
    merged.producer_name = "touchreal decoders train"
    merged.doc_string = meta.get("description", "")
    set_metadata(merged, meta)
    onnx.checker.check_model(merged)
    return merged


def set_metadata(model: onnx.ModelProto, meta: dict[str, Any]) -> None:
    """Embed ``meta`` (JSON) under :data:`META_KEY`, replacing any earlier value."""
    keep = [p for p in model.metadata_props if p.key != META_KEY]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    onnx.helper.set_model_props(model, {**{p.key: p.value for p in keep}, META_KEY: json.dumps(meta, sort_keys=True)})
