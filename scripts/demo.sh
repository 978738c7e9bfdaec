#!/usr/bin/env bash
# The main job on a fresh machine: build rayd and rayctl, start rayd with the CPU backend and its embedded defaults,
# build the shared Stanford bunny with rayctl, trace a 1024×1024 camera batch, render bunny.png, then stop rayd.
set -euo pipefail
cd "$(dirname "$0")/.."

cargo build --release --locked -p rayd-server -p rayd-client
bin=target/release
mesh=../shared/data/meshes/stanford-bunny.obj
work=target/demo
mkdir -p "$work"

"$bin/rayd" >"$work/rayd.out" 2>"$work/rayd.log" &
rayd_pid=$!
trap 'kill -TERM $rayd_pid 2>/dev/null || true; wait $rayd_pid 2>/dev/null || true' EXIT
for _ in $(seq 100); do
  "$bin/rayctl" devices >/dev/null 2>&1 && break
  kill -0 $rayd_pid 2>/dev/null || { cat "$work/rayd.log"; exit 1; }
  sleep 0.1
done
head -n 1 "$work/rayd.out"

set -x
"$bin/rayctl" devices
"$bin/rayctl" build --mesh "$mesh" --name bunny
"$bin/rayctl" rays --accel bunny --width 1024 --height 1024 --ray-format origin_tmin_direction_tmax -o "$work/rays.bin"
"$bin/rayctl" --json trace --accel bunny --rays "$work/rays.bin" \
  --ray-format origin_tmin_direction_tmax --hit-format t_triid_u_v --out "$work/hits.bin"
"$bin/rayctl" render --accel bunny --width 800 --height 600 -o bunny.png
