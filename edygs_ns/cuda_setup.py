"""The CUDA path's set-up: toolkit discovery, ``CUDA_HOME``, gsplat's kernels, and their diagnosis.

gsplat 1.4.0 ships no compiled kernels: at the first CUDA call it JIT-compiles them with
``torch.utils.cpp_extension.load``, which takes the toolkit root from ``CUDA_HOME`` or, unset, from
the folder above the first ``nvcc`` on the PATH. Where ``nvcc`` is a link or wrapper outside the
toolkit (``/usr/local/bin/nvcc`` -> ``/usr/local/cuda-13.0/bin/nvcc``) torch derives
``/usr/local``, and the C++ binding fails after the long kernel build with ``cuda_runtime.h: No
such file or directory``. ``ensure_cuda_home`` sets ``CUDA_HOME`` to the real toolkit root (the one
holding ``include/cuda_runtime.h``; ``nvcc`` itself reports it) before gsplat builds.

``require_gsplat_kernels`` is what training calls before the first gsplat rasterisation: it
fails at once, in one line naming the fix, when the kernels are missing and cannot be built,
instead of a long JIT build ending in an error (or an AttributeError on ``None`` without a
toolkit). ``collect_report`` / ``diagnose`` are the ``edygs-doctor`` command's logic and
``build_plan`` its ahead-of-time build (``--build-gsplat``).

Nothing here imports torch or gsplat at module level: ``scripts/setup_env.sh`` runs
``python -m edygs_ns.cuda_setup`` to print the toolkit root cheaply.
"""

from __future__ import annotations

import glob
import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Mapping, MutableMapping, Optional, Sequence

#: the header whose absence breaks gsplat's C++ binding (ext.cpp) under a wrong CUDA_HOME
RUNTIME_HEADER = Path("include") / "cuda_runtime.h"
#: toolkit roots tried after CUDA_HOME / CUDA_PATH and nvcc's own answer, in order
DEFAULT_TOOLKITS = ("/usr/local/cuda", "/usr/local/cuda-*", "/opt/cuda")
#: the name gsplat 1.4.0 JIT-builds its extension under (``gsplat/cuda/_backend.py``)
GSPLAT_EXTENSION = "gsplat_cuda"
#: written next to an ahead-of-time build: the torch / Python / CUDA / arch it was built for
BUILD_STAMP = "edygs_build.json"
#: the fix named by every "gsplat's kernels are unavailable" message
FIX_HINT = ("run `edygs-doctor` for the cause and `edygs-doctor --build-gsplat` to build gsplat's kernels "
            "ahead of time, or train with `--pipeline.model.rasterizer torch` (the torch rasteriser, slower)")
#: what a full build of gsplat's 24 sources took on the 2-core CPU machine (MAX_JOBS=2)
BUILD_TIME_NOTE = "about 40-60 min on 2 cores, a few minutes on 16"
_ARCH_RE = re.compile(r"^\d+\.\d+(\+PTX)?$")


class GsplatUnavailableError(RuntimeError):
    """gsplat's CUDA kernels are neither built nor buildable here (the message names the fix)."""


def require_device(device: object, cuda_available: Optional[Callable[[], bool]] = None) -> None:
    """Fail at once, in one line naming the fix, when training asks for a CUDA ``device`` that torch
    does not see (nerfstudio's ``--machine.device-type`` is ``cuda`` unless told otherwise)."""
    if not str(device).startswith("cuda"):
        return
    if cuda_available is None:
        import torch

        cuda_available = torch.cuda.is_available
    if not cuda_available():
        raise RuntimeError(f"training asks for {device} (nerfstudio's default device) but torch sees no CUDA GPU here; "
                           "on a CPU train with `ns-train edygs-cpu` or add `--machine.device-type cpu` "
                           "(`edygs-doctor` reports what torch and the toolkit see)")


# ----------------------------------------------------------------------------- the toolkit


def has_runtime_header(root: Optional[os.PathLike]) -> bool:
    """Whether ``root`` is a CUDA toolkit root with ``include/cuda_runtime.h``."""
    return root is not None and str(root) != "" and (Path(root) / RUNTIME_HEADER).is_file()


def find_nvcc(environ: Mapping[str, str] = os.environ) -> Optional[str]:
    """The first ``nvcc`` on ``environ``'s PATH (as torch and gsplat find it), or None."""
    return shutil.which("nvcc", path=environ.get("PATH", os.defpath))


def nvcc_reported_root(nvcc: str, timeout: float = 20.0) -> Optional[str]:
    """The toolkit root nvcc itself uses (``TOP`` of a dry run), which sees through wrappers and
    links; None when nvcc does not answer."""
    try:
        run = subprocess.run([nvcc, "-dryrun", "-c", "-x", "cu", os.devnull, "-o", os.devnull],
                             capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.SubprocessError):
        return None
    match = re.search(r"^#\$ TOP=(.+)$", run.stdout + run.stderr, re.MULTILINE)
    return os.path.normpath(match.group(1).strip().strip('"')) if match else None


def nvcc_version(nvcc: str, timeout: float = 20.0) -> Optional[str]:
    """``release X.Y, VX.Y.Z`` from ``nvcc --version``, or None."""
    try:
        run = subprocess.run([nvcc, "--version"], capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.SubprocessError):
        return None
    match = re.search(r"release [^\n]+", run.stdout)
    return match.group(0).strip() if match else None


def torch_derived_cuda_home(environ: Mapping[str, str], nvcc: Optional[str]) -> Optional[str]:
    """The CUDA_HOME torch's ``cpp_extension`` derives (its ``_find_cuda_home`` on Linux):
    CUDA_HOME / CUDA_PATH, else the folder above nvcc's folder (links not followed), else
    /usr/local/cuda where it exists."""
    home = environ.get("CUDA_HOME") or environ.get("CUDA_PATH")
    if home is None:
        if nvcc is not None:
            home = os.path.dirname(os.path.dirname(nvcc))
        else:
            home = DEFAULT_TOOLKITS[0] if os.path.exists(DEFAULT_TOOLKITS[0]) else None
    return home


def toolkit_candidates(environ: Mapping[str, str], nvcc: Optional[str],
                       reported_root: Callable[[str], Optional[str]] = nvcc_reported_root) -> List[str]:
    """Possible toolkit roots, best first: CUDA_HOME / CUDA_PATH, the root nvcc reports, the folder
    above the resolved nvcc, then the usual install folders (newest ``cuda-*`` first)."""
    found: List[Optional[str]] = [environ.get("CUDA_HOME"), environ.get("CUDA_PATH")]
    if nvcc is not None:
        found += [reported_root(nvcc), os.path.dirname(os.path.dirname(os.path.realpath(nvcc)))]
    for pattern in DEFAULT_TOOLKITS:
        found += sorted(glob.glob(pattern), reverse=True) if "*" in pattern else [pattern]
    unique: List[str] = []
    for root in found:
        if root and os.path.normpath(root) not in unique:
            unique.append(os.path.normpath(root))
    return unique


def find_toolkit_root(environ: Mapping[str, str], nvcc: Optional[str],
                      reported_root: Callable[[str], Optional[str]] = nvcc_reported_root) -> Optional[str]:
    """The first candidate root with ``include/cuda_runtime.h``, or None."""
    for root in toolkit_candidates(environ, nvcc, reported_root):
        if has_runtime_header(root):
            # name it by the stable link when that is the same toolkit (/usr/local/cuda -> cuda-13.0)
            stable = DEFAULT_TOOLKITS[0]
            if root != stable and os.path.realpath(stable) == os.path.realpath(root):
                return stable
            return root
    return None


def ensure_cuda_home(environ: MutableMapping[str, str] = os.environ,
                     reported_root: Callable[[str], Optional[str]] = nvcc_reported_root) -> Optional[str]:
    """Set CUDA_HOME to the real toolkit root when the one torch would derive lacks
    ``include/cuda_runtime.h`` (and put its ``bin`` on the PATH when no nvcc is there, as gsplat
    looks for nvcc on the PATH). Also patches ``torch.utils.cpp_extension.CUDA_HOME`` when that
    module is already imported (it reads the variable once). Returns a one-line note of what
    changed, or None when nothing needed changing or no toolkit was found."""
    nvcc = find_nvcc(environ)
    derived = torch_derived_cuda_home(environ, nvcc)
    if nvcc is not None and has_runtime_header(derived):
        return None
    root = find_toolkit_root(environ, nvcc, reported_root)
    if root is None:
        return None
    notes = []
    if not has_runtime_header(derived):
        environ["CUDA_HOME"] = root
        notes.append(f"CUDA_HOME={root} (torch would derive {derived or 'none'}, which has no {RUNTIME_HEADER})")
    if nvcc is None and os.path.isfile(os.path.join(root, "bin", "nvcc")):
        environ["PATH"] = os.path.join(root, "bin") + os.pathsep + environ.get("PATH", "")
        notes.append(f"PATH starts with {root}/bin (no nvcc was on the PATH)")
    cpp = sys.modules.get("torch.utils.cpp_extension")
    if cpp is not None and environ is os.environ and getattr(cpp, "CUDA_HOME", None) != environ.get("CUDA_HOME", root):
        cpp.CUDA_HOME = environ.get("CUDA_HOME", root)
    return "; ".join(notes) or None


# ----------------------------------------------------------------------------- gsplat's kernels


def _quiet_cpp_extension():
    """``torch.utils.cpp_extension``, imported without its "No CUDA runtime is found, using
    CUDA_HOME=..." warning (the doctor reports CUDA_HOME itself)."""
    import logging

    if "torch.utils.cpp_extension" in sys.modules:
        return sys.modules["torch.utils.cpp_extension"]
    logger = logging.getLogger("torch.utils.cpp_extension")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        import torch.utils.cpp_extension as cpp
    finally:
        logger.setLevel(level)
    return cpp


def extension_build_dir(environ: Mapping[str, str] = os.environ) -> Optional[Path]:
    """Where gsplat's JIT build lives (torch's ``_get_build_directory`` for ``gsplat_cuda``, not
    created here): $TORCH_EXTENSIONS_DIR/gsplat_cuda, else
    ~/.cache/torch_extensions/py{XY}_cu{ZZZ}/gsplat_cuda. None without torch."""
    try:
        import torch
    except ImportError:
        return None
    get_default_build_root = _quiet_cpp_extension().get_default_build_root
    root = environ.get("TORCH_EXTENSIONS_DIR")
    if root is None:
        accel = f"cu{torch.version.cuda.replace('.', '')}" if torch.version.cuda else "cpu"
        python = f"py{sys.version_info.major}{sys.version_info.minor}{getattr(sys, 'abiflags', '')}"
        root = os.path.join(get_default_build_root(), f"{python}_{accel}")
    return Path(root) / GSPLAT_EXTENSION


def build_fingerprint() -> Dict[str, Optional[str]]:
    """What a build of gsplat's extension is tied to: torch, its CUDA, Python (ABI)."""
    import torch

    return {"torch": torch.__version__, "torch_cuda": torch.version.cuda,
            "python": f"{sys.version_info.major}.{sys.version_info.minor}{getattr(sys, 'abiflags', '')}"}


@dataclass
class GsplatState:
    """gsplat's version and whether its CUDA kernels exist / import."""

    version: Optional[str] = None
    prebuilt: bool = False
    """gsplat.csrc exists (a wheel built with its kernels)"""
    build_dir: Optional[str] = None
    built: bool = False
    """the JIT build's gsplat_cuda.so exists in build_dir"""
    importable: Optional[bool] = None
    """the extension imported (None: not tried)"""
    import_error: Optional[str] = None
    stamp: Optional[Dict[str, object]] = None
    """BUILD_STAMP of an ahead-of-time build (torch / Python / arch it was built for)"""
    stamp_mismatch: Optional[str] = None
    """how the stamp differs from this torch / Python, or None"""


def gsplat_state(environ: Mapping[str, str] = os.environ, try_import: bool = True) -> GsplatState:
    """gsplat's kernels here, without starting a build (gsplat's ``_backend`` is not imported)."""
    import importlib.metadata
    import importlib.util

    state = GsplatState()
    try:
        state.version = importlib.metadata.version("gsplat")
    except importlib.metadata.PackageNotFoundError:
        return state
    try:
        state.prebuilt = importlib.util.find_spec("gsplat.csrc") is not None
    except (ImportError, ValueError):
        state.prebuilt = False
    build_dir = extension_build_dir(environ)
    if build_dir is not None:
        state.build_dir = str(build_dir)
        state.built = (build_dir / f"{GSPLAT_EXTENSION}.so").is_file()
        stamp_file = build_dir / BUILD_STAMP
        if stamp_file.is_file():
            try:
                state.stamp = json.loads(stamp_file.read_text())
            except ValueError:
                state.stamp = None
        if state.stamp is not None:
            here = build_fingerprint()
            diffs = [f"{k} {state.stamp.get(k)} (here {v})" for k, v in here.items() if state.stamp.get(k) != v]
            state.stamp_mismatch = "built for " + ", ".join(diffs) if diffs else None
    if try_import and (state.prebuilt or state.built):
        try:
            if state.prebuilt:
                import gsplat.csrc  # noqa: F401
            else:
                from torch.utils.cpp_extension import _import_module_from_library

                _import_module_from_library(GSPLAT_EXTENSION, str(build_dir), True)
            state.importable = True
        except Exception as exc:  # noqa: BLE001 - any import failure is the diagnosis
            state.importable = False
            state.import_error = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    return state


_KERNELS_READY = False


def require_gsplat_kernels(environ: MutableMapping[str, str] = os.environ,
                           state: Optional[Callable[[], GsplatState]] = None) -> None:
    """Make sure gsplat's CUDA kernels load before the first gsplat rasterisation.

    Sets CUDA_HOME (``ensure_cuda_home``), then imports gsplat's backend, which loads a built
    extension or JIT-compiles one. Raises GsplatUnavailableError (one line naming the fix) at
    once when nothing is built and no toolkit with ``cuda_runtime.h`` could build it, and when
    the build or the import fails. Runs once per process when it succeeds.
    """
    global _KERNELS_READY
    if _KERNELS_READY:
        return
    ensure_cuda_home(environ)
    found = (state or (lambda: gsplat_state(environ, try_import=False)))()
    if found.version is None:
        raise GsplatUnavailableError(f"gsplat is not installed; {FIX_HINT}")
    if not (found.prebuilt or found.built):
        nvcc = find_nvcc(environ)
        if nvcc is None:
            raise GsplatUnavailableError(
                f"gsplat's CUDA kernels are not built and no CUDA toolkit (nvcc) is here to build them; {FIX_HINT}")
        if not has_runtime_header(environ.get("CUDA_HOME") or torch_derived_cuda_home(environ, nvcc)):
            raise GsplatUnavailableError(
                f"gsplat's CUDA kernels are not built and the toolkit of {nvcc} has no {RUNTIME_HEADER} "
                f"(set CUDA_HOME to the toolkit root); {FIX_HINT}")
        from nerfstudio.utils.rich_utils import CONSOLE

        CONSOLE.log(f"[yellow][edygs] gsplat's CUDA kernels are not built: compiling them now ({BUILD_TIME_NOTE}; "
                    "next time build them ahead with `edygs-doctor --build-gsplat`)")
    try:
        from gsplat.cuda._backend import _C
    except Exception as exc:  # noqa: BLE001 - a failed JIT build surfaces as many types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise GsplatUnavailableError(f"gsplat's CUDA kernels failed to build or load ({type(exc).__name__}: {first}); {FIX_HINT}") from exc
    if _C is None:
        raise GsplatUnavailableError(f"gsplat's CUDA kernels are unavailable (gsplat found no toolkit to build them); {FIX_HINT}")
    _KERNELS_READY = True


# ----------------------------------------------------------------------------- the doctor


@dataclass
class Report:
    """What ``edygs-doctor`` reports: torch, the GPU, the toolkit, gsplat."""

    python: str = ""
    torch: Optional[str] = None
    torch_cuda: Optional[str] = None
    """CUDA runtime torch was built with (None: a CPU build)"""
    cuda_available: bool = False
    gpu: Optional[str] = None
    gpu_arch: Optional[str] = None
    """compute capability, e.g. "9.0" (None without a GPU)"""
    nvcc: Optional[str] = None
    nvcc_resolved: Optional[str] = None
    nvcc_version: Optional[str] = None
    cuda_home_env: Optional[str] = None
    torch_cuda_home: Optional[str] = None
    """what torch's cpp_extension would use"""
    torch_cuda_home_ok: bool = False
    """torch_cuda_home has include/cuda_runtime.h"""
    toolkit_root: Optional[str] = None
    """the root edygs uses (first with cuda_runtime.h), or None"""
    gsplat: GsplatState = field(default_factory=GsplatState)


def collect_report(environ: Mapping[str, str] = os.environ, try_import: bool = True) -> Report:
    """Everything the doctor prints, read from this machine (nothing is changed or built)."""
    report = Report(python=sys.version.split()[0])
    try:
        import torch

        report.torch, report.torch_cuda = torch.__version__, torch.version.cuda
        report.cuda_available = bool(torch.cuda.is_available())
        if report.cuda_available:
            report.gpu = torch.cuda.get_device_name(0)
            major, minor = torch.cuda.get_device_capability(0)
            report.gpu_arch = f"{major}.{minor}"
    except ImportError:
        pass
    report.nvcc = find_nvcc(environ)
    if report.nvcc is not None:
        report.nvcc_resolved = nvcc_reported_root(report.nvcc) or os.path.realpath(report.nvcc)
        report.nvcc_version = nvcc_version(report.nvcc)
    report.cuda_home_env = environ.get("CUDA_HOME") or environ.get("CUDA_PATH")
    report.torch_cuda_home = torch_derived_cuda_home(environ, report.nvcc)
    report.torch_cuda_home_ok = has_runtime_header(report.torch_cuda_home)
    report.toolkit_root = find_toolkit_root(environ, report.nvcc)
    if report.torch is not None:
        report.gsplat = gsplat_state(environ, try_import=try_import)
    return report


@dataclass
class Diagnosis:
    """One verdict: ``level`` ok / warn / error, a line saying what is wrong and the fix."""

    level: str
    line: str
    fix: Optional[str] = None


def _major(version: Optional[str]) -> Optional[str]:
    match = re.search(r"(\d+)\.\d+", version or "")
    return match.group(1) if match else None


def diagnose(report: Report) -> List[Diagnosis]:
    """The doctor's verdicts, the decisive one first."""
    out: List[Diagnosis] = []
    g = report.gsplat
    if report.torch is None:
        return [Diagnosis("error", "torch is not installed", "bash scripts/setup_env.sh")]
    if report.torch_cuda is None:
        return [Diagnosis("ok", "torch is a CPU build: training runs on CPU with the torch rasteriser (no CUDA path)",
                          "for a GPU install a CUDA build of torch (pyproject pins the version)")]
    kernels_ok = (g.prebuilt or g.built) and g.importable is not False
    if g.version is None:
        out.append(Diagnosis("error", "gsplat is not installed: the CUDA rasteriser is missing", "bash scripts/setup_env.sh"))
    elif (g.prebuilt or g.built) and g.importable is False:
        out.append(Diagnosis("error", f"gsplat's extension in {g.build_dir} does not import ({g.import_error})"
                             + (f"; {g.stamp_mismatch}" if g.stamp_mismatch else ""),
                             "rebuild it for this torch: edygs-doctor --build-gsplat"))
    elif kernels_ok:
        where = "a prebuilt gsplat.csrc" if g.prebuilt else f"built in {g.build_dir}"
        arch = f" for sm {g.stamp.get('arch')}" if g.stamp and g.stamp.get("arch") else ""
        if report.cuda_available:
            out.append(Diagnosis("ok", f"ready: gsplat's CUDA kernels ({where}{arch}) import; ns-train edygs uses them on {report.gpu}"))
        else:
            out.append(Diagnosis("ok", f"gsplat's CUDA kernels ({where}{arch}) import; no GPU here, so training runs on CPU "
                                 "with the torch rasteriser"))
        if g.stamp_mismatch:
            out.append(Diagnosis("warn", f"the build stamp says {g.stamp_mismatch}", "edygs-doctor --build-gsplat"))
    elif report.toolkit_root is None:
        level = "error" if report.cuda_available else "warn"
        what = (f"nvcc ({report.nvcc}) has no toolkit with {RUNTIME_HEADER} (tried CUDA_HOME, nvcc's root, /usr/local/cuda*)"
                if report.nvcc else "no CUDA toolkit (nvcc) found")
        out.append(Diagnosis(level, f"{what}: gsplat's CUDA kernels are not built and cannot be built here"
                             + ("" if report.cuda_available else " (no GPU here either: CPU training is unaffected)"),
                             f"install the CUDA {report.torch_cuda} toolkit (nvcc and headers) and run edygs-doctor --build-gsplat, "
                             "set CUDA_HOME to its root, or train with --pipeline.model.rasterizer torch"))
    elif not report.torch_cuda_home_ok:
        out.append(Diagnosis("warn", f"torch would use CUDA_HOME={report.torch_cuda_home or 'none'}, which has no "
                             f"{RUNTIME_HEADER}: a plain gsplat build fails ('cuda_runtime.h: No such file or directory'); "
                             f"edygs sets CUDA_HOME={report.toolkit_root} itself before gsplat builds; kernels not built yet",
                             f"export CUDA_HOME={report.toolkit_root}; edygs-doctor --build-gsplat"
                             + ("" if report.cuda_available else " --arch 9.0")))
    else:
        out.append(Diagnosis("warn", f"gsplat's CUDA kernels are not built: the first CUDA step would JIT-compile them ({BUILD_TIME_NOTE})",
                             "edygs-doctor --build-gsplat" + ("" if report.cuda_available else " --arch 9.0")))
    if report.nvcc_version and _major(report.nvcc_version.replace("release ", "")) != _major(report.torch_cuda):
        out.append(Diagnosis("warn", f"nvcc is {report.nvcc_version} but torch was built with CUDA {report.torch_cuda}: "
                             "torch refuses to build extensions across CUDA major versions",
                             f"install the CUDA {report.torch_cuda} toolkit, or the torch build for nvcc's CUDA"))
    return out


def format_report(report: Report, verdicts: Sequence[Diagnosis]) -> str:
    """The doctor's printout: one line per component, then the diagnosis and the fix."""
    g = report.gsplat
    rows = [
        ("python", report.python),
        ("torch", f"{report.torch or 'not installed'}" + (f" (CUDA runtime {report.torch_cuda})" if report.torch_cuda else " (CPU build)")),
        ("GPU", f"{report.gpu} (sm {report.gpu_arch})" if report.cuda_available else "none (torch.cuda.is_available() is False)"),
        ("nvcc", (f"{report.nvcc}" + (f" -> toolkit {report.nvcc_resolved}" if report.nvcc_resolved else "")
                  + (f" ({report.nvcc_version})" if report.nvcc_version else "")) if report.nvcc else "not on PATH"),
        ("CUDA_HOME", (f"set to {report.cuda_home_env}" if report.cuda_home_env else "unset")
         + f"; torch would use {report.torch_cuda_home or 'none'} ("
         + ("cuda_runtime.h found" if report.torch_cuda_home_ok else "no include/cuda_runtime.h") + ")"),
        ("toolkit", f"{report.toolkit_root} (include/cuda_runtime.h found; edygs uses it)" if report.toolkit_root
         else "none with include/cuda_runtime.h"),
        ("gsplat", "not installed" if g.version is None else (
            f"{g.version}; prebuilt kernels: {'yes' if g.prebuilt else 'no'}; JIT build {g.build_dir}: "
            + ("built" if g.built else "not built")
            + ("" if g.importable is None else ("; imports" if g.importable else f"; does not import ({g.import_error})"))
            + (f"; stamp: sm {g.stamp.get('arch')}, torch {g.stamp.get('torch')}" if g.stamp else ""))),
    ]
    width = max(len(k) for k, _ in rows)
    lines = ["edygs-doctor"] + [f"  {k.ljust(width)}  {v}" for k, v in rows]
    for d in verdicts:
        lines.append(f"diagnosis ({d.level}): {d.line}")
        if d.fix:
            lines.append(f"  fix: {d.fix}")
    return "\n".join(lines)


def report_dict(report: Report, verdicts: Sequence[Diagnosis]) -> Dict[str, object]:
    """JSON form of the report and verdicts."""
    return {"report": asdict(report), "diagnosis": [asdict(d) for d in verdicts]}


# ----------------------------------------------------------------------------- ahead-of-time build

#: run in a fresh interpreter with the build environment: imports gsplat's backend, which builds
#: (or loads) the extension with torch's JIT machinery, then prints where it is
BUILD_SNIPPET = (
    "import sys\n"
    "from gsplat.cuda._backend import _C\n"
    "if _C is None:\n"
    "    sys.exit('gsplat built nothing: no nvcc on the PATH')\n"
    "print('built:', getattr(_C, '__file__', _C))\n"
)
#: checks, in another fresh interpreter, that the build imports (no GPU needed)
IMPORT_SNIPPET = (
    "import sys\n"
    "from torch.utils.cpp_extension import _import_module_from_library\n"
    "m = _import_module_from_library(sys.argv[1], sys.argv[2], True)\n"
    "print('imports:', m.__file__)\n"
)


@dataclass
class BuildPlan:
    """How ``edygs-doctor --build-gsplat`` builds gsplat's extension: a command and its environment."""

    command: List[str]
    env_changes: Dict[str, str]
    build_dir: Path
    arch: str
    arch_source: str
    """"the GPU", "--arch" or a default"""
    jobs: int

    def environment(self, base: Mapping[str, str] = os.environ) -> Dict[str, str]:
        return {**base, **self.env_changes}

    def shell(self) -> str:
        """The same build as one shell line (for the printout)."""
        import shlex

        env = " ".join(f"{k}={shlex.quote(v)}" for k, v in self.env_changes.items() if k != "PATH")
        if "PATH" in self.env_changes:
            env = f"PATH={shlex.quote(self.env_changes['PATH'].split(os.pathsep)[0])}:$PATH {env}"
        return f"{env} {shlex.quote(self.command[0])} -c \"from gsplat.cuda._backend import _C\""


#: default arch without a GPU: H100 / H200 (Hopper), the kind this project's GPU checks target
DEFAULT_ARCH = "9.0"


def parse_arch(arch: str) -> str:
    """Normalise an arch list ("9.0", "8.6 9.0", "8.0;9.0+PTX") to TORCH_CUDA_ARCH_LIST's form."""
    parts = [p for p in re.split(r"[;\s,]+", arch.strip()) if p]
    bad = [p for p in parts if not _ARCH_RE.match(p)]
    if not parts or bad:
        raise ValueError(f"--arch {arch!r}: expected compute capabilities like 9.0 or '8.6;9.0+PTX'")
    return ";".join(parts)


def default_jobs(cpu_count: Optional[int] = None, mem_bytes: Optional[int] = None) -> int:
    """MAX_JOBS: one per core, at most one per 2 GiB of memory (nvcc jobs take 1-2 GiB each)."""
    cpus = cpu_count or os.cpu_count() or 1
    if mem_bytes is None:
        try:
            mem_bytes = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            mem_bytes = 0
    by_memory = max(1, mem_bytes // (2 << 30)) if mem_bytes else cpus
    return max(1, min(cpus, by_memory))


def build_plan(arch: Optional[str] = None, jobs: Optional[int] = None, extensions_dir: Optional[Path] = None,
               environ: Mapping[str, str] = os.environ, gpu_arch: Optional[str] = None,
               reported_root: Callable[[str], Optional[str]] = nvcc_reported_root,
               python: str = sys.executable) -> BuildPlan:
    """The ahead-of-time build of gsplat's extension.

    Args:
        arch: TORCH_CUDA_ARCH_LIST to build for (e.g. "9.0"); default the GPU's (``gpu_arch``),
            else DEFAULT_ARCH, so it can be built on a machine without a GPU.
        jobs: MAX_JOBS (parallel nvcc processes); default ``default_jobs()``.
        extensions_dir: TORCH_EXTENSIONS_DIR (the build lands in its gsplat_cuda/); default torch's
            cache. A folder inside the repository can travel to another machine (same torch,
            Python and CUDA there).

    Raises:
        ValueError: no toolkit with ``include/cuda_runtime.h`` is found, or ``arch`` is malformed.
    """
    nvcc = find_nvcc(environ)
    root = find_toolkit_root(environ, nvcc, reported_root)
    if root is None:
        raise ValueError(f"no CUDA toolkit with {RUNTIME_HEADER} found (nvcc: {nvcc or 'not on PATH'}); "
                         "install the toolkit or set CUDA_HOME to its root")
    if arch is not None:
        arch_list, source = parse_arch(arch), "--arch"
    elif gpu_arch is not None:
        arch_list, source = parse_arch(gpu_arch), "the GPU"
    else:
        arch_list, source = DEFAULT_ARCH, "default (no GPU here: H100/H200; pass --arch for others)"
    changes = {"CUDA_HOME": root, "TORCH_CUDA_ARCH_LIST": arch_list, "MAX_JOBS": str(jobs or default_jobs())}
    if nvcc is None or os.path.dirname(os.path.dirname(os.path.realpath(nvcc))) != os.path.realpath(root):
        changes["PATH"] = os.path.join(root, "bin") + os.pathsep + environ.get("PATH", "")
    if extensions_dir is not None:
        changes["TORCH_EXTENSIONS_DIR"] = str(Path(extensions_dir).resolve())
    build_dir = extension_build_dir({**environ, **changes})
    return BuildPlan(command=[python, "-c", BUILD_SNIPPET], env_changes=changes,
                     build_dir=build_dir if build_dir is not None else Path(changes.get("TORCH_EXTENSIONS_DIR", "?")),
                     arch=arch_list, arch_source=source, jobs=int(changes["MAX_JOBS"]))


def run_build(plan: BuildPlan, environ: Mapping[str, str] = os.environ,
              runner: Callable[..., subprocess.CompletedProcess] = subprocess.run) -> Path:
    """Run ``plan``, check in a fresh interpreter that the extension imports, write BUILD_STAMP
    next to it; returns the build folder. Raises RuntimeError when a step fails."""
    env = plan.environment(environ)
    built = runner(plan.command, env=env)
    if built.returncode != 0:
        raise RuntimeError(f"gsplat's build failed (exit {built.returncode}); see the compiler output above")
    check = runner([plan.command[0], "-c", IMPORT_SNIPPET, GSPLAT_EXTENSION, str(plan.build_dir)], env=env)
    if check.returncode != 0:
        raise RuntimeError(f"gsplat's extension in {plan.build_dir} was built but does not import")
    from datetime import datetime, timezone

    stamp = {**build_fingerprint(), "arch": plan.arch, "max_jobs": plan.jobs, "cuda_home": plan.env_changes["CUDA_HOME"],
             "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}
    plan.build_dir.mkdir(parents=True, exist_ok=True)
    (plan.build_dir / BUILD_STAMP).write_text(json.dumps(stamp, indent=2) + "\n")
    return plan.build_dir


def main() -> None:
    """``python -m edygs_ns.cuda_setup``: one line on the toolkit root (scripts/setup_env.sh);
    with ``--cuda-home``: only the CUDA_HOME to export (empty when torch derives a right one)."""
    nvcc = find_nvcc()
    if sys.argv[1:] == ["--cuda-home"]:
        root = find_toolkit_root(os.environ, nvcc)
        print(root if root and not has_runtime_header(torch_derived_cuda_home(os.environ, nvcc)) else "")
        return
    if nvcc is None and find_toolkit_root(os.environ, None) is None:
        print("[setup] no CUDA toolkit (nvcc): training uses the CPU (edygs-doctor explains the CUDA path)")
        return
    derived = torch_derived_cuda_home(os.environ, nvcc)
    root = find_toolkit_root(os.environ, nvcc)
    if root is None:
        print(f"[setup] nvcc {nvcc} has no toolkit with {RUNTIME_HEADER}: gsplat cannot build (run edygs-doctor)")
    elif has_runtime_header(derived):
        print(f"[setup] CUDA toolkit {root}: torch derives CUDA_HOME={derived} (fine)")
    else:
        print(f"[setup] CUDA toolkit {root}: torch would derive CUDA_HOME={derived}, which lacks {RUNTIME_HEADER}; "
              f"edygs sets CUDA_HOME={root} before gsplat builds (export it for other tools); "
              "build gsplat's kernels ahead with: .venv/bin/edygs-doctor --build-gsplat")


if __name__ == "__main__":
    main()
