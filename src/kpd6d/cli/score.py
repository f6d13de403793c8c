"""``kpd6d-score RESULTS.csv DATASET_ROOT [--json PATH] [--decompose]``: BOP19 scores (AR_MSSD, AR_MSPD) of a results file.

Follows the BOP toolkit (see :mod:`kpd6d.evaluation.bop19`); prints a per-object table. VSD is not
computed (it needs depth images and a depth renderer) and the output says so. ``--decompose`` also
scores the estimates with their depth, translation or rotation taken from the ground truth
(:mod:`kpd6d.evaluation.decompose`): where the score is lost.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from kpd6d.io import atomic_write_text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="kpd6d-score", description=__doc__.strip().splitlines()[0])
    p.add_argument("results", type=Path, help="BOP results CSV (scene_id,im_id,obj_id,score,R,t,time)")
    p.add_argument("root", type=Path, help="BOP dataset root (with test_targets_bop19.json, models_eval/ or models/)")
    p.add_argument("--json", type=Path, default=None, help="write the scores as JSON here")
    p.add_argument("--split", default="test", help="split folder under the root (default: test)")
    p.add_argument("--targets", default="test_targets_bop19.json", help="targets file name in the root")
    p.add_argument("--visib-gt-min", type=float, default=-1.0,
                   help="GT instances with visib_fract below this are not counted; negative (default, as the "
                        "BOP toolkit): the inst_count most visible instances of each target are counted")
    p.add_argument("--decompose", action="store_true",
                   help="also score the estimates with their depth / translation / rotation from the ground truth "
                        "(where the score is lost; a diagnosis)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from kpd6d.evaluation import bop19
    from kpd6d.evaluation.results_io import ResultsFormatError

    try:
        where = dict(split=args.split, targets_filename=args.targets, visib_gt_min=args.visib_gt_min)
        scores = bop19.score_bop19_file(args.results, args.root, **where)
        if args.decompose:
            from kpd6d.evaluation.decompose import error_decomposition, format_decomposition
            from kpd6d.evaluation.results_io import read_bop_results

            scores["decomposition"] = error_decomposition(read_bop_results(args.results), args.root, **where)
    except (bop19.BopScoringError, ResultsFormatError) as exc:
        print(f"kpd6d-score: {exc}", file=sys.stderr)
        return 2
    scores["results"] = str(args.results)
    scores["dataset_root"] = str(args.root)
    print(bop19.format_scores_table(scores) + "\n\n" + bop19.format_scores_summary(scores))
    if "decomposition" in scores:
        print("\nwhere the score is lost (one part of each pose from the nearest GT instance):\n"
              + format_decomposition(scores["decomposition"]))
    if args.json:
        atomic_write_text(args.json, json.dumps(scores, indent=2))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
