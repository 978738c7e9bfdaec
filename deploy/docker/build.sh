#!/usr/bin/env bash
# Builds rayd and rayctl and copies them to OUT_DIR. The image's build stage runs exactly this (PROFILE=release);
# deploy/check.sh runs it too (PROFILE=dev, to stay fast), so a command that breaks here breaks CI first.
#   deploy/docker/build.sh OUT_DIR   env: PROFILE (release|dev, default release), CARGO_FEATURES (rayd's, optional)
set -euo pipefail
out=${1:?usage: build.sh OUT_DIR}
profile=${PROFILE:-release}
features=()
if [[ -n "${CARGO_FEATURES:-}" ]]; then features=(--features "$CARGO_FEATURES"); fi
# One package at a time, as the end-to-end tests build them: the same feature sets, so CI reuses their build.
cargo build --locked --profile "$profile" --bins -p rayd-server "${features[@]}"
cargo build --locked --profile "$profile" --bins -p rayd-client
dir=$([[ $profile == dev ]] && echo debug || echo "$profile")
mkdir -p "$out"
install -m 0755 "${CARGO_TARGET_DIR:-target}/$dir/rayd" "${CARGO_TARGET_DIR:-target}/$dir/rayctl" "$out/"
