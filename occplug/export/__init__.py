"""Export of a model's inference path (``torch.export`` or ONNX) and the parity check against the eager model.

The exported graph is :class:`InferenceWrapper`: the camera inputs of one frame -> class ids and
logits on the evaluation grid. Calibration and image augmentation are graph **inputs**, and the
geometry that depends on them (frustum points, voxel indices) is recomputed inside the graph, so
one export serves any camera rig of the same image size and camera count.

The lift-splat splat (:class:`occplug.ops.FrustumSplatter`) normally pools through plans cached
per geometry: the cache key is a hash of the calibration's bytes, computed on the host. That step
cannot be traced: ``torch.export`` stops at it (a data-dependent guard on the depth-centre check,
then the host copy for the hash), so a cached plan can never end up in a graph as a constant.
While exporting, every splatter runs its ``reference`` path instead (the same frustum geometry,
pooled with ``index_add_`` over all points: equal up to float summation order), which is plain
tensor code on the inputs. ONNX gets that ``index_add`` as ``ScatterElements`` (:func:`~occplug.export.tracing._index_add_as_scatter_add`):
onnxruntime's CPU ``ScatterND(reduction="add")`` races on duplicate indices, so a graph holding one is refused.
The parity check runs the eager model with its own (cached) path on
the original frames and on frames with perturbed intrinsics, extrinsics and image augmentation,
so an export that baked one rig's geometry in would fail it.

A model that reads **LiDAR** (a point encoder) also takes :data:`POINT_INPUTS`: the points, NaN-padded to
the longest cloud of the batch, with the point count a dynamic dimension, and the LiDAR -> ego pose. Its point
encoders must trace with any point count: drop points by pooling them into a discard row, not by boolean
indexing (the core's ``voxel_points`` does so), and treat non-finite rows as no point.

A **streaming** model (a component holding a :class:`occplug.streams.StreamState`) exports as
:class:`StreamingWrapper`: one step of the stream, its state an explicit input and output. Besides
:data:`INPUTS` the graph takes :data:`STREAM_INPUTS` (this frame's and the previous frame's pose,
timestamp and frame index, and ``is_start``) and the previous state (``prev_state.<name>``), and
returns the new state (``state.<name>``) after ``class_ids`` and ``logits``; feed the outputs of one
frame back as the inputs of the next (:func:`stream_inputs`). The reset rules of
:class:`~occplug.streams.StreamState` are in the graph (a frame-index step outside
``1..max_frame_step``, a time step outside ``(0, max_gap_s]``), except the one on strings: the
caller says ``is_start`` at the first frame and wherever the scene changes. Poses come in as
``ego_to_global`` float64, as the eager state keeps them, and the relative motion is computed in
float64 inside the graph as eager computes it (float32 global poses, hundreds of metres off the
origin, would round the translation before the subtraction; both exporters and onnxruntime take
float64 matmuls). While exporting, every ``StreamState`` is replaced by an :class:`ExplicitStream`
reading those inputs, and a component whose forward branches on the reset mask (``if reset.any()``,
boolean-mask indexing: data-dependent, untraceable) runs a branch-free equivalent (its own
``export_forward``, as the core's ``dense_voxels_history`` does). The parity check runs the frames as a
sequence in order (each also perturbed, as a second sequence), feeding the exported state back, and
compares the state too.

A component that declares ``stateful = True`` but keeps its state outside a ``StreamState`` is
refused with one line naming it.

The package, by concept:

* :mod:`~occplug.export.graph`: what the exported graph is (its inputs and outputs, the wrappers, the streams'
  stand-ins, the refusals);
* :mod:`~occplug.export.tracing`: tracing, the ``torch.export`` and ONNX artefacts, the ONNX decompositions, the
  one-line explanations of a failure;
* :mod:`~occplug.export.parity_check`: the parity check against the eager model and its report;
* :mod:`~occplug.export.checkpoint`: ``occplug export`` from a checkpoint.
"""

from .checkpoint import check_out, export_checkpoint
from .graph import (
    FORMATS,
    INPUTS,
    OUTPUTS,
    POINT_INPUTS,
    STREAM_INPUTS,
    ExplicitStream,
    ExportError,
    InferenceWrapper,
    StreamingWrapper,
    check_exportable,
    example_inputs,
    export_ready,
    graph_inputs,
    inputs_of,
    is_streaming,
    occupancy_logits,
    pad_points,
    reads_points,
    stream_inputs,
)
from .parity_check import (
    MAX_LOGIT_DIFF,
    MIN_CLASS_AGREEMENT,
    one_line,
    parity,
    passes,
    perturb,
    report_path,
    stream_parity,
)
from .tracing import export_model, load_exported, trace

__all__ = [
    "FORMATS",
    "INPUTS",
    "MAX_LOGIT_DIFF",
    "MIN_CLASS_AGREEMENT",
    "OUTPUTS",
    "POINT_INPUTS",
    "STREAM_INPUTS",
    "ExplicitStream",
    "ExportError",
    "InferenceWrapper",
    "StreamingWrapper",
    "check_exportable",
    "check_out",
    "example_inputs",
    "export_checkpoint",
    "export_model",
    "export_ready",
    "graph_inputs",
    "inputs_of",
    "is_streaming",
    "load_exported",
    "occupancy_logits",
    "one_line",
    "pad_points",
    "parity",
    "passes",
    "perturb",
    "reads_points",
    "report_path",
    "stream_inputs",
    "stream_parity",
    "trace",
]
