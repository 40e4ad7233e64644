"""scripts/gpu_bundle.sh's ``use`` mode (the device side): unpacks the bundle and prints the export
that puts it and the working tree on PYTHONPATH; a missing bundle is a one-line error. (``make``
downloads wheels and compiles gsplat for 30-50 min: not run in CI.)"""

from __future__ import annotations

import io
import json
import subprocess
import tarfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "gpu_bundle.sh"


def _use(out: Path, site: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), "use", "--out", str(out)], capture_output=True, text=True,
                          env={"PATH": "/usr/bin:/bin", "EDYGS_SITE": str(site), "HOME": str(out)})


def test_use_unpacks_the_bundle_and_prints_the_export(tmp_path):
    out = tmp_path / "bundle"
    out.mkdir()
    payload = b"WHERE = 'bundle'\n"
    with tarfile.open(out / "site.tar.xz", "w:xz") as tar:
        info = tarfile.TarInfo("./edygs_bundle_probe.py")
        info.size = len(payload)
        tar.addfile(info, io.BytesIO(payload))
    (out / "bundle.json").write_text(json.dumps({"python": "0.1", "torch": "0.0.1"}))
    site = tmp_path / "site"
    site.mkdir()
    (site / "stale.py").write_text("")  # an earlier unpack is replaced, not mixed in
    run = _use(out, site)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == f"export PYTHONPATH={ROOT}:{site}"
    assert (site / "edygs_bundle_probe.py").read_bytes() == payload and not (site / "stale.py").exists()
    assert "bundle made for python/torch 0.1 0.0.1" in run.stderr  # no machine has those


def test_use_without_a_bundle_says_which_file_is_missing(tmp_path):
    run = _use(tmp_path / "nothing", tmp_path / "site")
    assert run.returncode == 1 and run.stdout == ""
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and str(tmp_path / "nothing" / "site.tar.xz") in lines[0] and "gpu_bundle.sh make" in lines[0]
