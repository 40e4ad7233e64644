"""Merge the results of several ``benchmarks/suite.py`` runs into one table.

    python benchmarks/suite_merge.py OUT A/results.json B/results.json ...

Rows are keyed by (row label, preset, seed, training seed); a later file replaces an earlier file's row with the
same key, so list older runs first. Every row keeps the file it came from (``source``), and
OUT.json / OUT.md list the files with their commands and dates. The per-preset means, suite
means and done-means checks are computed as ``suite.py`` computes them.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Dict, List, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent))

from suite import DEFAULT_TRAIN_SEED, markdown, scene_presets, summarise  # noqa: E402

Key = Tuple[str, str, int, int]


def merge(paths: List[Path]) -> Dict[str, Any]:
    """The rows and references of every results.json in ``paths`` (later ones win), summarised."""
    rows: Dict[Key, Dict[str, Any]] = {}
    refs: Dict[Key, Dict[str, Any]] = {}
    sources: List[Dict[str, str]] = []
    for path in paths:
        try:
            results = json.loads(path.read_text())
            for label, entries in results["rows"].items():
                for row in entries:
                    rows[(label, row["preset"], int(row["seed"]), int(row.get("train_seed", DEFAULT_TRAIN_SEED)))] = dict(row, source=str(path))
            for label, entries in results.get("references", {}).items():
                for row in entries:
                    refs[(label, row["preset"], int(row["seed"]), DEFAULT_TRAIN_SEED)] = dict(row, source=str(path))
        except (OSError, ValueError, KeyError) as err:
            raise SystemExit(f"suite_merge: {path}: not a suite.py results.json ({err})")
        sources.append({"file": str(path), "command": results.get("command", "?"), "date": results.get("date", "?"),
                        "machine": results.get("machine", "?")})
    merged: Dict[str, Any] = {"sources": sources, "rows": {}, "references": {}, "missing": [], "failures": []}
    order = {name: i for i, name in enumerate(scene_presets())}

    def place(item: Tuple[Key, Dict[str, Any]]) -> Tuple[int, str, int, int]:
        _, preset, seed, train_seed = item[0]
        return order.get(preset, len(order)), preset, seed, train_seed

    for (label, *_), row in sorted(rows.items(), key=place):
        merged["rows"].setdefault(label, []).append(row)
    for (label, *_), row in sorted(refs.items(), key=place):
        merged["references"].setdefault(label, []).append(row)
    return summarise(merged)


def main() -> None:
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    out = Path(sys.argv[1])
    merged = merge([Path(p) for p in sys.argv[2:]])
    runs = "\n".join(f"- `{s['file']}`: `{s['command']}`, {s['date']}, {s['machine']}" for s in merged["sources"])
    per_row = "\n".join(f"- {label} {row['preset']} seed {row['seed']}, training seed {row.get('train_seed', DEFAULT_TRAIN_SEED)}: `{row['source']}`"
                        for label, entries in merged["rows"].items() for row in entries)
    out.with_suffix(".json").write_text(json.dumps(merged, indent=2))
    out.with_suffix(".md").write_text(f"Merged by `benchmarks/suite_merge.py` from (later files win):\n\n{runs}\n\n"
                                      f"{markdown(merged)}\n\nWhere each row comes from:\n\n{per_row}\n")
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
