"""Build and load the compiled CPU rasteriser (``csrc/raster_cpu.cpp``) once per machine.

The C++ source ships in the package and is compiled on first use with
``torch.utils.cpp_extension.load`` (g++ and ninja, both needed only then); the shared library is
cached under torch's extensions directory (``$TORCH_EXTENSIONS_DIR``, default
``~/.cache/torch_extensions``) and later processes load it in well under a second. It is built
for the CPU it runs on (``-march=native``); the module name carries a hash of the CPU's model
and instruction-set flags, so a cache shared by different machines holds one build per CPU kind
instead of loading code with instructions the CPU lacks, and a hash of the source and flags, so
processes running different versions of the source do not rebuild over each other. See docs/cpu_rasterizer.md.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import platform
import time
from pathlib import Path
from types import ModuleType
from typing import Optional

from nerfstudio.utils.rich_utils import CONSOLE

#: the kernel source, shipped as package data.
SOURCE = Path(__file__).with_name("csrc") / "raster_cpu.cpp"
#: compiler flags: optimised, vectorised for this CPU, OpenMP over tiles; no FP traps, so the
#: compiler may evaluate both sides of a select (else the backward loop stays scalar).
CFLAGS = ("-O3", "-march=native", "-fno-trapping-math", "-fno-math-errno", "-fopenmp")
LDFLAGS = ("-fopenmp",)
#: environment variable that disables the compiled backend ("1": use the torch rasteriser).
DISABLE_ENV = "EDYGS_NO_COMPILED_RASTERIZER"


def cpu_tag() -> str:
    """Short hash of the CPU model and instruction-set flags (the build is -march=native)."""
    text = platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags", "Features", "CPU part"))]
        text += "".join(sorted(set(lines)))
    except OSError:
        text += platform.processor()
    return hashlib.sha1(text.encode()).hexdigest()[:10]


def source_tag() -> str:
    """Short hash of the kernel source, its path and the compiler flags. The path counts because
    torch's loader rebuilds a module whose source list changed: two checkouts of one version
    sharing a name would rebuild over each other in turn."""
    text = SOURCE.read_bytes() + str(SOURCE.resolve()).encode() + " ".join(CFLAGS + LDFLAGS).encode()
    return hashlib.sha1(text).hexdigest()[:8]


def module_name() -> str:
    """Extension name: one build per CPU kind and per source version. Processes running different
    versions of the source (another checkout, a long run started before an edit) each find their
    own build in the cache instead of rebuilding over each other's."""
    return f"edygs_raster_cpu_{cpu_tag()}_{source_tag()}"


@functools.lru_cache(maxsize=1)
def load_extension() -> Optional[ModuleType]:
    """The compiled module, built on first use; None (with one logged line) when it cannot be built."""
    if os.environ.get(DISABLE_ENV, "") not in ("", "0"):
        CONSOLE.log(f"compiled CPU rasteriser off ({DISABLE_ENV} is set); using the torch rasteriser")
        return None
    start = time.perf_counter()
    try:
        quiet = logging.getLogger("torch.utils.cpp_extension")  # "No CUDA runtime" on CPU machines
        level = quiet.level
        quiet.setLevel(logging.ERROR)
        try:
            from torch.utils import cpp_extension
        finally:
            quiet.setLevel(level)

        module = cpp_extension.load(
            name=module_name(), sources=[str(SOURCE)], extra_cflags=list(CFLAGS),
            extra_ldflags=list(LDFLAGS), verbose=False,
        )
    except Exception as error:  # no compiler, no ninja, a failed build: fall back, one line
        reason = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
        CONSOLE.log(f"[yellow]compiled CPU rasteriser unavailable ({reason[:160]}); using the torch rasteriser[/yellow]")
        return None
    took = time.perf_counter() - start
    if took > 5.0:  # a build, not a cache hit
        CONSOLE.log(f"compiled CPU rasteriser built in {took:.0f} s (cached for later runs)")
    return module
