"""The CUDA path without a GPU: toolkit / CUDA_HOME discovery, edygs-doctor's diagnosis, the
ahead-of-time build's command, the clear failure when gsplat's kernels are missing, the torch
rasteriser on any device (fake toolkits under tmp_path, monkeypatched availability)."""

from __future__ import annotations

import json
import os
import stat
import sys
import types
from pathlib import Path

import pytest
import torch

from edygs_ns import cuda_setup
from edygs_ns.cuda_setup import GsplatState, GsplatUnavailableError, Report


def fake_toolkit(tmp_path: Path, headers: bool = True) -> dict:
    """/usr/local/bin/nvcc as a wrapper exec'ing <tmp>/cuda-13.0/bin/nvcc (as on this project's
    machines), a fake nvcc answering -dryrun and --version; returns the paths and an environ."""
    root = tmp_path / "cuda-13.0"
    (root / "bin").mkdir(parents=True)
    if headers:
        (root / "include").mkdir()
        (root / "include" / "cuda_runtime.h").write_text("/* fake */\n")
    real = root / "bin" / "nvcc"
    real.write_text(f"#!/bin/sh\necho 'Cuda compilation tools, release 13.0, V13.0.88'\n"
                    f"echo '#$ _HERE_={root}/bin' >&2\necho '#$ TOP={root}/bin/..' >&2\n")
    wrapper_dir = tmp_path / "usr" / "local" / "bin"
    wrapper_dir.mkdir(parents=True)
    wrapper = wrapper_dir / "nvcc"
    wrapper.write_text(f"#!/bin/sh\nexec {real} \"$@\"\n")
    for f in (real, wrapper):
        f.chmod(f.stat().st_mode | stat.S_IEXEC)
    return {"root": str(root), "wrapper": str(wrapper), "environ": {"PATH": f"{wrapper_dir}:/usr/bin:/bin"}}


@pytest.fixture(autouse=True)
def no_system_toolkits(monkeypatch, tmp_path):
    """Hide this machine's /usr/local/cuda* from the search; forget any earlier kernel check."""
    monkeypatch.setattr(cuda_setup, "DEFAULT_TOOLKITS", (str(tmp_path / "none" / "cuda"), str(tmp_path / "none" / "cuda-*")))
    monkeypatch.setattr(cuda_setup, "_KERNELS_READY", False)


def test_wrapper_nvcc_gives_a_wrong_torch_cuda_home_that_ensure_fixes(tmp_path):
    tk = fake_toolkit(tmp_path)
    env = dict(tk["environ"])
    nvcc = cuda_setup.find_nvcc(env)
    assert nvcc == tk["wrapper"]
    # torch's rule: the folder above nvcc's folder, here <tmp>/usr/local, without the header
    assert cuda_setup.torch_derived_cuda_home(env, nvcc) == str(tmp_path / "usr" / "local")
    assert cuda_setup.nvcc_reported_root(nvcc) == tk["root"]
    assert cuda_setup.find_toolkit_root(env, nvcc) == tk["root"]
    note = cuda_setup.ensure_cuda_home(env)
    assert env["CUDA_HOME"] == tk["root"] and "CUDA_HOME" in note
    assert cuda_setup.ensure_cuda_home(env) is None  # now right: nothing to change


def test_a_wrong_cuda_home_is_replaced_and_a_right_one_kept(tmp_path):
    tk = fake_toolkit(tmp_path)
    env = dict(tk["environ"], CUDA_HOME=str(tmp_path / "usr" / "local"))
    cuda_setup.ensure_cuda_home(env)
    assert env["CUDA_HOME"] == tk["root"]
    other = tmp_path / "other-cuda"
    (other / "include").mkdir(parents=True)
    (other / "include" / "cuda_runtime.h").write_text("")
    env = dict(tk["environ"], CUDA_HOME=str(other))
    assert cuda_setup.ensure_cuda_home(env) is None and env["CUDA_HOME"] == str(other)


def test_no_nvcc_on_path_puts_the_toolkit_bin_first(tmp_path, monkeypatch):
    tk = fake_toolkit(tmp_path)
    monkeypatch.setattr(cuda_setup, "DEFAULT_TOOLKITS", (tk["root"],))
    env = {"PATH": "/usr/bin:/bin"}
    cuda_setup.ensure_cuda_home(env)
    assert env["PATH"].split(os.pathsep)[0] == os.path.join(tk["root"], "bin")


def _report(tmp_path, environ, monkeypatch, gsplat=GsplatState(version="1.4.0"), gpu=False) -> Report:
    monkeypatch.setattr(cuda_setup, "gsplat_state", lambda environ=None, try_import=True: gsplat)
    report = cuda_setup.collect_report(environ)
    report.torch, report.torch_cuda = "2.14.1+cu130", "13.0"
    report.cuda_available, report.gpu, report.gpu_arch = (True, "NVIDIA H200", "9.0") if gpu else (False, None, None)
    return report


def test_doctor_diagnoses_the_wrong_cuda_home(tmp_path, monkeypatch):
    tk = fake_toolkit(tmp_path)
    report = _report(tmp_path, tk["environ"], monkeypatch)
    assert report.nvcc == tk["wrapper"] and report.toolkit_root == tk["root"] and not report.torch_cuda_home_ok
    first = cuda_setup.diagnose(report)[0]
    assert first.level == "warn" and "no include/cuda_runtime.h" in first.line
    assert f"export CUDA_HOME={tk['root']}" in first.fix and "--build-gsplat --arch 9.0" in first.fix
    text = cuda_setup.format_report(report, cuda_setup.diagnose(report))
    assert "torch would use" in text and "diagnosis (warn)" in text and "release 13.0" in text


@pytest.mark.parametrize("gpu", [False, True])
def test_doctor_diagnoses_a_missing_toolkit(tmp_path, monkeypatch, gpu):
    report = _report(tmp_path, {"PATH": "/nonexistent"}, monkeypatch, gpu=gpu)
    assert report.nvcc is None and report.toolkit_root is None
    first = cuda_setup.diagnose(report)[0]
    assert first.level == ("error" if gpu else "warn")
    assert "no CUDA toolkit (nvcc) found" in first.line
    assert "--pipeline.model.rasterizer torch" in first.fix and "CUDA 13.0 toolkit" in first.fix


def test_doctor_diagnoses_nvcc_without_headers(tmp_path, monkeypatch):
    tk = fake_toolkit(tmp_path, headers=False)
    first = cuda_setup.diagnose(_report(tmp_path, tk["environ"], monkeypatch, gpu=True))[0]
    assert first.level == "error" and "has no toolkit with include/cuda_runtime.h" in first.line


def test_doctor_verdicts_on_built_and_broken_kernels(tmp_path, monkeypatch):
    tk = fake_toolkit(tmp_path)
    ok = GsplatState(version="1.4.0", built=True, importable=True, build_dir="/b", stamp={"arch": "9.0"})
    first = cuda_setup.diagnose(_report(tmp_path, tk["environ"], monkeypatch, gsplat=ok, gpu=True))[0]
    assert first.level == "ok" and "ready" in first.line and "sm 9.0" in first.line
    broken = GsplatState(version="1.4.0", built=True, importable=False, build_dir="/b", import_error="ImportError: undefined symbol",
                         stamp_mismatch="built for torch 2.11.0 (here 2.14.1+cu130)")
    first = cuda_setup.diagnose(_report(tmp_path, tk["environ"], monkeypatch, gsplat=broken, gpu=True))[0]
    assert first.level == "error" and "does not import" in first.line and "2.11.0" in first.line
    cpu = Report(torch="2.14.1+cpu", torch_cuda=None)
    assert cuda_setup.diagnose(cpu)[0].line.startswith("torch is a CPU build")


def test_doctor_cli_prints_and_writes_json(tmp_path, monkeypatch, capsys):
    from edygs_ns.scripts.doctor import DoctorCommand

    tk = fake_toolkit(tmp_path)
    monkeypatch.setenv("PATH", tk["environ"]["PATH"])
    monkeypatch.delenv("CUDA_HOME", raising=False)
    monkeypatch.delenv("CUDA_PATH", raising=False)
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    assert DoctorCommand(json_out=tmp_path / "doctor.json", build_gsplat=True, dry_run=True, jobs=3).main() == 0
    out = capsys.readouterr().out
    assert "edygs-doctor" in out and "diagnosis" in out and "gsplat" in out
    assert f"CUDA_HOME={tk['root']}" in out and "TORCH_CUDA_ARCH_LIST=9.0" in out and "MAX_JOBS=3" in out
    data = json.loads((tmp_path / "doctor.json").read_text())
    assert data["report"]["toolkit_root"] == tk["root"] and data["diagnosis"]


def test_build_plan_environment(tmp_path):
    tk = fake_toolkit(tmp_path)
    env = tk["environ"]
    plan = cuda_setup.build_plan(arch="8.6 9.0+PTX", jobs=4, extensions_dir=tmp_path / "ext", environ=env, python="/py")
    assert plan.env_changes["TORCH_CUDA_ARCH_LIST"] == "8.6;9.0+PTX" and plan.arch_source == "--arch"
    assert plan.env_changes["MAX_JOBS"] == "4" and plan.env_changes["CUDA_HOME"] == tk["root"]
    assert plan.env_changes["PATH"].split(os.pathsep)[0] == os.path.join(tk["root"], "bin")
    assert plan.env_changes["TORCH_EXTENSIONS_DIR"] == str((tmp_path / "ext").resolve())
    assert plan.build_dir == (tmp_path / "ext").resolve() / "gsplat_cuda"
    assert plan.command[:2] == ["/py", "-c"] and "gsplat.cuda._backend" in plan.command[2]
    assert cuda_setup.build_plan(environ=env, gpu_arch="9.0").arch_source == "the GPU"
    no_gpu = cuda_setup.build_plan(environ=env)
    assert no_gpu.arch == "9.0" and no_gpu.arch_source.startswith("default") and no_gpu.jobs >= 1
    with pytest.raises(ValueError, match="compute capabilities"):
        cuda_setup.build_plan(arch="sm_90", environ=env)
    with pytest.raises(ValueError, match="no CUDA toolkit"):
        cuda_setup.build_plan(environ={"PATH": "/nonexistent"})
    assert cuda_setup.default_jobs(cpu_count=16, mem_bytes=8 << 30) == 4


def test_run_build_checks_the_import_and_stamps(tmp_path):
    tk = fake_toolkit(tmp_path)
    plan = cuda_setup.build_plan(arch="9.0", jobs=2, extensions_dir=tmp_path / "ext", environ=tk["environ"], python="/py")
    calls = []

    def runner(cmd, env):
        calls.append((cmd, env))
        return types.SimpleNamespace(returncode=0)

    where = cuda_setup.run_build(plan, tk["environ"], runner=runner)
    assert [c[0][2] for c in calls] == [cuda_setup.BUILD_SNIPPET, cuda_setup.IMPORT_SNIPPET]
    assert all(c[1]["TORCH_CUDA_ARCH_LIST"] == "9.0" and c[1]["CUDA_HOME"] == tk["root"] for c in calls)
    stamp = json.loads((where / cuda_setup.BUILD_STAMP).read_text())
    assert stamp["arch"] == "9.0" and stamp["torch"] == torch.__version__
    with pytest.raises(RuntimeError, match="build failed"):
        cuda_setup.run_build(plan, tk["environ"], runner=lambda cmd, env: types.SimpleNamespace(returncode=1))


def test_gsplat_state_reads_a_stamp_for_another_torch(tmp_path):
    build = tmp_path / "ext" / "gsplat_cuda"
    build.mkdir(parents=True)
    (build / cuda_setup.BUILD_STAMP).write_text(json.dumps({**cuda_setup.build_fingerprint(), "torch": "2.11.0", "arch": "9.0"}))
    state = cuda_setup.gsplat_state({"TORCH_EXTENSIONS_DIR": str(tmp_path / "ext")}, try_import=False)
    assert state.version and not state.built and state.build_dir == str(build)
    assert "torch 2.11.0" in state.stamp_mismatch


# ----------------------------------------------------------------------------- failure / fallback


def _no_kernels(monkeypatch, tmp_path, built=False):
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    monkeypatch.delenv("CUDA_HOME", raising=False)
    monkeypatch.delenv("CUDA_PATH", raising=False)
    monkeypatch.setattr(cuda_setup, "gsplat_state", lambda environ=None, try_import=True: GsplatState(version="1.4.0", built=built))


def test_cuda_training_fails_at_once_naming_the_fix_without_kernels(monkeypatch, tmp_path):
    from edygs_ns.render.contract import select_backend

    _no_kernels(monkeypatch, tmp_path)
    with pytest.raises(GsplatUnavailableError) as info:
        select_backend(torch.device("cuda"))  # "auto" on CUDA picks gsplat
    message = str(info.value)
    assert "\n" not in message and "no CUDA toolkit" in message
    assert "edygs-doctor --build-gsplat" in message and "--pipeline.model.rasterizer torch" in message
    with pytest.raises(GsplatUnavailableError):
        select_backend(torch.device("cuda"), "gsplat")


def test_rasterizer_torch_on_cuda_skips_gsplat(monkeypatch, tmp_path):
    from edygs_ns.render.contract import select_backend
    from edygs_ns.render.torch_backend import rasterize_torch

    _no_kernels(monkeypatch, tmp_path)
    assert select_backend(torch.device("cuda"), "torch") is rasterize_torch
    assert select_backend(torch.device("cpu")).__name__ in ("rasterize_cpu", "rasterize_torch")  # never gsplat


def test_a_failed_build_or_an_empty_backend_is_one_clear_line(monkeypatch, tmp_path):
    _no_kernels(monkeypatch, tmp_path, built=True)  # "built", so the backend is imported
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", types.SimpleNamespace(_C=None))
    with pytest.raises(GsplatUnavailableError, match="unavailable.*edygs-doctor --build-gsplat"):
        cuda_setup.require_gsplat_kernels()
    class FailedBuild:  # gsplat's JIT build failing as on this machine without CUDA_HOME
        @property
        def _C(self):
            raise RuntimeError("Error building extension 'gsplat_cuda'\nmore compiler output")

    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", FailedBuild())
    with pytest.raises(GsplatUnavailableError, match="failed to build or load \\(RuntimeError: Error building extension 'gsplat_cuda'\\);") as info:
        cuda_setup.require_gsplat_kernels()
    assert "\n" not in str(info.value)
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", types.SimpleNamespace(_C=object()))
    cuda_setup.require_gsplat_kernels()
    assert cuda_setup._KERNELS_READY


def test_torch_rasteriser_makes_no_tensor_on_the_default_device():
    """Device-agnostic: with the default device set to 'meta', any tensor the rasteriser made
    without an explicit device would be a meta tensor and break the CPU computation; the
    forward and backward must still match the plain CPU run exactly (so on CUDA tensors every
    intermediate stays on the GPU)."""
    from edygs_ns.render.torch_backend import rasterize_torch

    g = torch.Generator().manual_seed(0)
    n, w, h = 150, 40, 30
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([2.0, 1.5, 1.0]) + torch.tensor([0.0, 0.0, 4.0])
    scene = {"means": means, "quats": torch.randn(n, 4, generator=g), "scales": 0.02 + 0.1 * torch.rand(n, 3, generator=g),
             "opacities": 0.1 + 0.85 * torch.rand(n, generator=g), "features": torch.rand(n, 4, generator=g)}
    viewmats = torch.eye(4)[None].repeat(2, 1, 1)
    viewmats[1, 0, 3] = -0.2
    ks = torch.tensor([[40.0, 0.0, w / 2], [0.0, 40.0, h / 2], [0.0, 0.0, 1.0]]).repeat(2, 1, 1)
    bg = torch.tensor([[0.3, 0.2, 0.1, 0.0], [1.0, 1.0, 1.0, 0.0]])

    def run():
        leaves = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
        out = rasterize_torch(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["features"],
                              viewmats, ks, w, h, backgrounds=bg)
        (out.render.sum() + (out.depth * out.alpha.detach()).sum() + out.alpha.sum()).backward()
        return out, {k: v.grad for k, v in leaves.items()}

    ref, ref_grads = run()
    torch.set_default_device("meta")
    try:
        out, grads = run()
    finally:
        torch.set_default_device(None)
    assert out.render.device.type == "cpu" and torch.equal(out.render, ref.render) and torch.equal(out.depth, ref.depth)
    for k in scene:
        assert torch.equal(grads[k], ref_grads[k]), k


def test_require_device_checks_only_cuda_devices():
    from edygs_ns.cuda_setup import require_device

    require_device("cpu", cuda_available=lambda: False)  # nothing to check
    require_device("cuda", cuda_available=lambda: True)
    with pytest.raises(RuntimeError, match="edygs-cpu"):
        require_device("cuda", cuda_available=lambda: False)
