"""ONNX export of the stateless reprojection modules, with symbolic batch and image sizes.

What is written for hard tests is the **export formulation** (:mod:`stereorepro.reproject._lean`): planar source
tables read with ``GatherElements`` on int32 indices of H·W elements per tap, accept tests as comparisons, the
reasons computed for the few pixels that need them, no image-sized ``Where`` in the taps; for
``StereoReprojection(rectified=True)`` two taps per pixel instead of four. Soft tests and motion vectors export the
general path as it is traced. Both give the torch reference's ``valid`` and ``reason`` exactly and its colours to
rounding (tests/reproject/test_export.py, in onnxruntime and in the ``onnx.reference`` evaluator).

onnxruntime notes: opset ≥ 17 is required (we default to 18); float32 graphs (the default, and what onnxruntime's
``ThresholdedRelu`` supports) and float64 graphs (``export_onnx(..., inputs=<float64 inputs>)``) both run; a graph
exported with float16 inputs widens them to float32 inside (tested with onnxruntime 1.32).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from torch import Tensor, nn

from .._extras import require
from .atomic import atomic_path

__all__ = ["export_onnx", "onnx_input_dims", "symbolic_axes"]


def symbolic_axes(fields) -> dict[str, dict[int, str]]:
    """``{input name: {axis: symbol}}`` of a module's ``input_fields`` (name and symbolic shape per input, e.g.
    ``Field("src_depth", ("B", "1", "Hp", "Wp"))``): every dimension named by letters stays symbolic, digits are
    fixed.

    Examples:
        >>> from stereorepro.io.onnx import symbolic_axes
        >>> from stereorepro.reproject.view import Field
        >>> symbolic_axes([Field("src_depth", ("B", "1", "Hp", "Wp")), Field("K", ("B", "3", "3"))])
        {'src_depth': {0: 'B', 2: 'Hp', 3: 'Wp'}, 'K': {0: 'B'}}
    """
    return {f.name: {axis: dim for axis, dim in enumerate(f.shape) if not dim.isdigit()} for f in fields}


def export_onnx(
    module: nn.Module, path, opset: int = 18, inputs: tuple[Tensor, ...] | None = None, check_symbolic: bool = True
) -> Path:
    """Export a stateless reprojection module to ONNX with symbolic B, H, W (and Hp, Wp for source images).

    Args:
        module: :class:`~stereorepro.StereoReprojection`, :class:`~stereorepro.TemporalReprojection`,
            :class:`~stereorepro.ReprojectionDenoiser`, or any module describing its forward's inputs as
            ``input_fields`` (name and symbolic shape each: :class:`stereorepro.reproject.view.Field`) and naming
            its outputs in ``output_names``.
        path: output file; written atomically (:func:`stereorepro.io.atomic.atomic_path`).
        opset: ONNX opset, ≥ 17.
        inputs: example inputs (default: ``stereorepro._testing.example_inputs``, an analytic scene).
        check_symbolic: verify that the exported image inputs really have symbolic B/H/W (the dynamo exporter
            can silently specialise them) and raise otherwise.

    Returns:
        the path written.

    Examples:
        >>> import tempfile, torch
        >>> from stereorepro import StereoReprojection, intrinsics_from_fov
        >>> from stereorepro.io.onnx import export_onnx, onnx_input_dims
        >>> depth = torch.full((1, 1, 2, 4), 2.0); normal = torch.zeros(1, 3, 2, 4); normal[:, 2] = -1
        >>> view = (depth, normal, intrinsics_from_fov(90.0, 4, 2), torch.eye(4)[None])
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     path = export_onnx(StereoReprojection(0.01, 0.1), f"{tmp}/stereo.onnx",
        ...                        inputs=(torch.ones(1, 3, 2, 4), *view, *view))
        ...     dims = onnx_input_dims(path)
        >>> path.name, dims["src_color"], dims["dst_depth"]  # batch and image size stay symbolic
        ('stereo.onnx', ['B', 3, 'Hp', 'Wp'], ['B', 1, 'H', 'W'])
    """
    if opset < 17:
        raise ValueError(f"opset must be >= 17 (GridSample/ReduceMax semantics), got {opset}")
    fields = tuple(getattr(module, "input_fields", ()))
    if not fields:
        raise TypeError(
            f"{type(module).__name__} has no `input_fields` (name and symbolic shape of each forward "
            "input); cannot export"
        )
    names = [f.name for f in fields]
    if inputs is None:
        from .._testing import example_inputs

        inputs = example_inputs(module)
    inputs = tuple(inputs)
    if len(inputs) != len(names):
        raise ValueError(f"expected {len(names)} inputs ({', '.join(names)}), got {len(inputs)}")
    require("onnx", "export_onnx")
    path = Path(path)
    dynamic_axes = symbolic_axes(fields)
    module = module.eval()
    with atomic_path(path) as tmp, warnings.catch_warnings():
        # torch's constant folding notes every strided Slice it leaves alone: known noise, the graph is correct
        warnings.filterwarnings("ignore", message="Constant folding - Only steps=1", category=UserWarning)
        torch.onnx.export(
            module,
            inputs,
            str(tmp),
            input_names=names,
            output_names=list(module.output_names),
            dynamic_axes=dynamic_axes,
            opset_version=opset,
            dynamo=False,
            do_constant_folding=True,
        )
        if check_symbolic:
            dims = onnx_input_dims(tmp)
            for n in names:
                for axis, sym in dynamic_axes[n].items():
                    if not isinstance(dims[n][axis], str):
                        raise RuntimeError(
                            f"export_onnx: input {n!r} axis {axis} was fixed to {dims[n][axis]} "
                            f"instead of symbolic {sym!r}"
                        )
    return path


def onnx_input_dims(path) -> dict[str, list]:
    """Input name → list of dims (int for fixed, str for symbolic) of an ONNX file.

    Examples:
        >>> import tempfile, onnx
        >>> from onnx import TensorProto, helper
        >>> from stereorepro.io.onnx import onnx_input_dims
        >>> x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["B", 3, "H", "W"])
        >>> y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["B", 3, "H", "W"])
        >>> graph = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "relu", [x], [y])
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     onnx.save(helper.make_model(graph), f"{tmp}/relu.onnx")
        ...     dims = onnx_input_dims(f"{tmp}/relu.onnx")
        >>> dims
        {'x': ['B', 3, 'H', 'W']}
    """
    onnx = require("onnx", "onnx_input_dims")
    model = onnx.load(str(path))
    out = {}
    for i in model.graph.input:
        out[i.name] = [d.dim_param if d.dim_param else d.dim_value for d in i.type.tensor_type.shape.dim]
    return out
