#!/usr/bin/env bash
# Reproduce the shipped materials: what `neumip fit MATERIAL -o models/MATERIAL.onnx` makes with no flags (the
# `maps` recipe for a material defined by maps, the paper's for flat), plus the one ablation the report's parallax
# checks need, rock_nooffset (`fit --no-offset --relief 0` on rock's data). Each fit resumes where it stopped when the
# same command is run again (its work folder, data and checkpoint, is models/NAME.run/, not committed).
#   bash models/make_models.sh                 # all six, one after another (about 20 min a 256^2 material on 2 cores)
#   bash models/make_models.sh rock rock_nooffset
# THREADS: torch threads of each training (default 1: on the 2-core machine two fits side by side beat one with two
# threads). FLAGS: more `neumip fit` flags for every model (e.g. FLAGS="--preset quality" or "--device cuda").
set -euo pipefail
NEUMIP=${NEUMIP:-.venv/bin/neumip}
THREADS=${THREADS:-1}
read -r -a flags <<< "${FLAGS:-}"
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(flat rock yarn turtle foam rock_nooffset)
for name in "${names[@]}"; do
  case "$name" in
    *_nooffset) material=${name%_nooffset}
                extra=(--no-offset --relief 0 --data "models/$material.run/data") ;;  # the parallax stages' ablation
    *) material=$name extra=() ;;
  esac
  "$NEUMIP" fit "$material" -o "models/$name.onnx" --force --threads "$THREADS" "${extra[@]}" ${flags[@]+"${flags[@]}"}
done
