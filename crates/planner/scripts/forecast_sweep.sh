#!/usr/bin/env bash
# The planner against the conventional 3-angle sets under the printed forecast (issue 33):
# 3 example scenes x 2 target/background pairs x 2 cameras x min separation 0/30/50 = 36
# cases of `polarimeter plan --scene`. Separation 0 runs with --detection-only (repeats
# allowed); 30 and 50 are Stokes sets. A case is lost when a conventional set that the same
# constraints allow (`allowed` in the output) has a higher forecast SCR than the chosen set
# (compared at 1e-9 relative: the two SCRs come from the same forecast code).
# Usage (from the workspace root, after `cargo build --release -p polar-cli`):
#   crates/planner/scripts/forecast_sweep.sh [path/to/polarimeter]
set -euo pipefail
bin=${1:-target/release/polarimeter}
cases=0
lost=0
printf '%-15s %-12s %-12s %-12s %4s %-28s %10s %10s %10s %s\n' scene camera target background sep angles_deg scr 0/45/90 0/60/120 verdict
for scene in rooftop rooftop_panels study; do
  case $scene in
    rooftop) pairs="panel:asphalt glass:asphalt" ;;
    rooftop_panels) pairs="metal:grass glass:asphalt" ;;
    study) pairs="black_paint:asphalt glass:asphalt" ;;
  esac
  for pair in $pairs; do
    target=${pair%%:*}
    background=${pair##*:}
    for camera in ccd_seed cmos_modern; do
      for sep in 0 30 50; do
        extra=()
        if [ "$sep" = 0 ]; then extra=(--detection-only); fi
        out=$("$bin" plan --scene "examples/$scene.toml" --camera "examples/cameras/$camera.toml" \
          --target "$target" --background "$background" --channels 3 \
          --min-separation-deg "$sep" "${extra[@]}")
        verdict=$(jq -r '
          .forecast.scr as $s
          | [.forecast.scr_conventional | to_entries[] | select(.value.allowed)
             | select(.value.scr > $s * (1 + 1e-9)) | .key]
          | if length == 0 then "ok" else "LOST to " + join(",") end' <<<"$out")
        line=$(jq -r '[(.angles_deg | map(. * 100 | round / 100) | map(tostring) | join("/")),
          (.forecast.scr | . * 100 | round / 100),
          (.forecast.scr_conventional["0/45/90"] | (.scr * 100 | round / 100 | tostring) + (if .allowed then "" else "*" end)),
          (.forecast.scr_conventional["0/60/120"] | (.scr * 100 | round / 100 | tostring) + (if .allowed then "" else "*" end))]
          | @tsv' <<<"$out")
        IFS=$'\t' read -r angles scr c1 c2 <<<"$line"
        printf '%-15s %-12s %-12s %-12s %4s %-28s %10s %10s %10s %s\n' "$scene" "$camera" "$target" "$background" "$sep" "$angles" "$scr" "$c1" "$c2" "$verdict"
        cases=$((cases + 1))
        if [ "$verdict" != ok ]; then lost=$((lost + 1)); fi
      done
    done
  done
done
echo "(* = not allowed by the constraints)"
echo "cases: $cases, lost to an allowed conventional set: $lost"
