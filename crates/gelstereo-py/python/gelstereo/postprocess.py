"""Marknet's input layout, decoding and post-processing, as the Rust localizer has them
(``gelstereo-markers``), for callers that run a Marknet network themselves (the trainer's PyTorch
and ONNX Runtime runs), and the YOLO baseline's (`yolo_postprocess`). The functions are the extension's; see each one's docstring.

Layouts are tuples ``(input_width, input_height, scaled_width, scaled_height, offset_x, offset_y)``;
markers float64 arrays ``(n, 3)`` of x, y (original px, (0, 0) = centre of the top-left pixel) and
confidence; images uint8 grey ``HxW`` or BGR ``HxWx3``.
"""

from ._gelstereo import _postprocess as _native

Marknet = _native.Marknet
default_post = _native.default_post
default_yolo_post = _native.default_yolo_post
fit_layout = _native.fit_layout
probe_layout = _native.probe_layout
input_per_px = _native.input_per_px
network_input = _native.network_input
decode = _native.decode
postprocess = _native.postprocess
lattice_fit = _native.lattice_fit
yolo_postprocess = _native.yolo_postprocess

MRE_NEIGHBOURS: int = _native.MRE_NEIGHBOURS
MRE_FEATURES: int = _native.MRE_FEATURES
MISSING_DISTANCE: float = _native.MISSING_DISTANCE
AREA_BELOW_SCALE: float = _native.AREA_BELOW_SCALE
FILL_SAMPLE_STEP: int = _native.FILL_SAMPLE_STEP
MAX_INPUT_SIDE_PX: int = _native.MAX_INPUT_SIDE_PX

__all__ = [
    "Marknet", "default_post", "default_yolo_post", "fit_layout", "probe_layout", "input_per_px", "network_input", "decode", "postprocess",
    "lattice_fit", "yolo_postprocess", "MRE_NEIGHBOURS", "MRE_FEATURES", "MISSING_DISTANCE", "AREA_BELOW_SCALE",
    "FILL_SAMPLE_STEP", "MAX_INPUT_SIDE_PX",
]
