#!/usr/bin/env bash
# The real UR10e of Mamedov et al. 2020 as kvark bags, the way a user brings in their own robot:
# the URDF from Universal Robots' ROS 2 description (ur10e xacro) through `kvark init`, each unloaded
# identification run through `kvark import` (examples/ur10e_mamedov2020_mapping.yaml).
#
#   bash scripts/ur10e_dataset.sh DIR
#
# writes DIR/config/ur10e.yaml (+ ur10e.urdf), DIR/bags/<run> for every run of dataset_ur10e/identification_data
# whose name has no "load" in it (the loaded runs are a test kept aside: never imported, never read), and clones the
# two repositories into DIR/src. The data has no licence: keep DIR outside the project. Sources (a URL or a local
# clone): KVARK_UR10E_DATASET (default https://github.com/shamilmamedov/dynamic_calibration) and
# KVARK_UR_DESCRIPTION (default https://github.com/UniversalRobots/Universal_Robots_ROS2_Description).
# Then, for example:
#   kvark benchmark --real DIR/bags/ur-20_02_19_14harm50sec --config DIR/config/ur10e.yaml --rate 0 --trim 2 6.5 \
#       --out results/ur10e
set -euo pipefail
if [ $# -ne 1 ]; then
    echo "usage: bash scripts/ur10e_dataset.sh DIR" >&2
    exit 2
fi
here="$(cd "$(dirname "$0")/.." && pwd)"
out="$(mkdir -p "$1" && cd "$1" && pwd)"
dataset="${KVARK_UR10E_DATASET:-https://github.com/shamilmamedov/dynamic_calibration}"
description="${KVARK_UR_DESCRIPTION:-https://github.com/UniversalRobots/Universal_Robots_ROS2_Description}"
mkdir -p "$out/src" "$out/bags"
[ -d "$out/src/dynamic_calibration" ] || git clone -q --depth 1 "$dataset" "$out/src/dynamic_calibration"
[ -d "$out/src/ur_description" ] || git clone -q --depth 1 "$description" "$out/src/ur_description"
kvark init --xacro "$out/src/ur_description/urdf/ur.urdf.xacro" --package-path "ur_description=$out/src/ur_description" \
    --xacro-arg ur_type:=ur10e --xacro-arg name:=ur --robot ur10e --ee-frame tool0 --out "$out/config/ur10e.yaml" --force
for log in "$out"/src/dynamic_calibration/dataset_ur10e/identification_data/*.csv; do
    name="$(basename "$log" .csv)"
    case "${name,,}" in *load*) continue ;; esac
    kvark import "$log" --mapping "$here/examples/ur10e_mamedov2020_mapping.yaml" --config "$out/config/ur10e.yaml" \
        --out "$out/bags/$name" --force
done
echo "ur10e_dataset: config $out/config/ur10e.yaml, $(ls "$out/bags" | wc -l) bags in $out/bags"
