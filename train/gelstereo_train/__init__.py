"""Training of Marknet and MRE (marker localization for GelStereo-type tactile sensors), ONNX export.

OpenMP threads spin while waiting by default; on a shared 2-core machine that starves the other
thread and other processes (measured here: 10 img/s instead of ~120 under load), so waiting threads
sleep unless the caller chose otherwise. This must be set before torch is imported.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
