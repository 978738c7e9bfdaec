#!/usr/bin/env bash
# Builds rayd and rayctl and copies them to OUT_DIR. The image's build stage runs exactly this (PROFILE=release);
# deploy/check.sh runs it too (PROFILE=dev, to stay fast), so a command that breaks here breaks CI first.
#   deploy/docker/build.sh OUT_DIR   env: PROFILE (release|dev, default release), CARGO_FEATURES (rayd's, optional)
set -euo pipefail
out=${1:?usage: build.sh OUT_DIR}
profile=${PROFILE:-release}
# One workspace build: a single feature resolution for both binaries. With PROFILE=dev (deploy/check.sh in CI) the
# test targets are named too (already built by `cargo test --workspace`): dependency features then resolve exactly as
# in the test build and only the two binaries are compiled.
targets=(--workspace --bins)
if [[ $profile == dev ]]; then targets+=(--tests); fi
features=()
if [[ -n "${CARGO_FEATURES:-}" ]]; then
  # rayd's features, named through its package in a workspace build.
  features=(--features "$(tr ', ' '\n\n' <<<"$CARGO_FEATURES" | sed '/^$/d; s|^|rayd-server/|' | paste -sd,)")
fi
cargo build --locked --profile "$profile" "${targets[@]}" "${features[@]}"
dir=$([[ $profile == dev ]] && echo debug || echo "$profile")
mkdir -p "$out"
install -m 0755 "${CARGO_TARGET_DIR:-target}/$dir/rayd" "${CARGO_TARGET_DIR:-target}/$dir/rayctl" "$out/"
