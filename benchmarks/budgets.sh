#!/usr/bin/env bash
# What each part buys at each budget (issue 52): sweeps/budgets.yaml's four paper rows and the two successors
# (hierarchical=proposal, encoding=hashgrid), 3 seeds each, on the built-in scene or on a Blender-format scene,
# then one report over all 18 runs against ablation=complete. Run alone on the machine (times are compared).
#   bash benchmarks/budgets.sh OUT_DIR                 # the built-in scene
#   bash benchmarks/budgets.sh OUT_DIR data=blender data.root=SCENE   # e.g. nerfexp-scene SCENE --scene glossy
set -euo pipefail
out=${1:?usage: budgets.sh OUT_DIR [OVERRIDE ...]}
shift
lscpu | grep -m1 "Model name" > /dev/null && lscpu | grep -m1 "Model name"
nerfexp +sweeps=budgets "$@" hydra.sweep.dir="$out/rows"
nerfexp +sweeps=budgets '~hydra.sweeper.params.ablation' hierarchical=proposal "$@" hydra.sweep.dir="$out/proposal"
nerfexp +sweeps=budgets '~hydra.sweeper.params.ablation' encoding=hashgrid "$@" hydra.sweep.dir="$out/hashgrid"
nerfexp-report "$out/rows" "$out/proposal" "$out/hashgrid" --out "$out/report" --reference ablation=complete
