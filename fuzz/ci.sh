#!/usr/bin/env bash
# Bounded fuzzing, as CI runs it (RELIABILITY.md, section 1): every cargo-fuzz target for RAYD_FUZZ_SECONDS
# (45 by default), two at a time, from the checked-in seeds in fuzz/seeds/ and whatever fuzz/corpus/ already holds.
# Built without a sanitizer on the stable toolchain (coverage instrumentation, debug assertions, opt-level 1): it
# compiles in about 3 minutes where the AddressSanitizer build of a long run by hand takes 17. A crash fails the
# script; its input is left in fuzz/artifacts/<target>/ and printed.
set -euo pipefail
cd "$(dirname "$0")"

seconds="${RAYD_FUZZ_SECONDS:-45}"
cargo_fuzz_version=0.13.2
if [[ "$(cargo fuzz --version 2>/dev/null)" != "cargo-fuzz $cargo_fuzz_version" ]]; then
  cargo install --locked --quiet "cargo-fuzz@$cargo_fuzz_version"
fi
build=(--dev --sanitizer none)
cargo fuzz build "${build[@]}"

# Runs one target for the time given and prints libFuzzer's final statistics.
run_target() {
  local target="$1" corpora=("corpus/$1")
  mkdir -p "corpus/$target"
  [[ -d "seeds/$target" ]] && corpora+=("seeds/$target")
  cargo fuzz run "${build[@]}" "$target" "${corpora[@]}" -- \
    -max_total_time="$seconds" -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 >"corpus/$target.log" 2>&1 || {
    echo "== fuzz target $target FAILED:"
    tail -n 60 "corpus/$target.log"
    return 1
  }
  echo "== fuzz target $target: $(grep -E '^stat::number_of_executed_units' "corpus/$target.log" | awk '{print $2}') runs," \
    "$(grep -E '^#[0-9]+.*DONE' "corpus/$target.log" | sed -E 's/.*(cov: [0-9]+).*(corp: [^ ]+).*(exec\/s: [0-9]+).*/\1 \2 \3/')"
}

status=0
for pair in "requests rays" "accel_blob meshes"; do
  pids=()
  for target in $pair; do
    run_target "$target" &
    pids+=($!)
  done
  for pid in "${pids[@]}"; do
    wait "$pid" || status=1
  done
done
exit "$status"
