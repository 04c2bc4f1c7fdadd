"""The vision core: templates, the estimate and its geometry (no web framework, no cache).

numba's parallel kernels run on OpenMP threads (vision/threads.py), which by default spin for
milliseconds after each kernel before they sleep. A frame runs dozens of short kernels between Python
steps, so a spinning thread took the second core from the frame's own background work (the
refinement's border trace, the interior check, the region evidence) and, when the machine was busy,
each kernel's end waited for a descheduled spinner (paper frames, distance given, on a loaded 2-core
machine: 346 ms p50 spinning, 89 ms sleeping). Threads sleep at once unless the environment says
otherwise; set before the OpenMP runtime loads (numba loads it with the first parallel kernel).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
