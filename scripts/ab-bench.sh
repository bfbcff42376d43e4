#!/usr/bin/env bash
# A/B comparison of two `precimap` binaries on one bench figure, for machines whose speed drifts
# from run to run (shared 2-core machines here swing ±15 %): the binaries run alternately, the
# order swapped every pair, and the result is the geometric mean of the per-pair ratios B/A with
# a 95 % interval (t distribution over the pairs' log ratios). A change is real when the
# interval excludes 1.
#
#   scripts/ab-bench.sh OLD_BINARY NEW_BINARY [PAIRS] [-- BENCH ARGUMENTS]
#
# Defaults: 4 pairs of `bench estimate --scale small --threads 1 --json`, comparing
# `estimate_points_per_cpu_s`. Another bench or field: e.g.
#   FIELD=preprocess_points_per_s_per_core scripts/ab-bench.sh a b 4 -- preprocess --scale small --repeat 1 --no-scaling --json
# Both binaries share the bench's cache (simulated campaign), so build it once first.
set -euo pipefail
if [ $# -lt 2 ]; then
    sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'
    exit 2
fi
a=$1
b=$2
shift 2
pairs=4
if [ $# -gt 0 ] && [ "$1" != "--" ]; then
    pairs=$1
    shift
fi
if [ $# -gt 0 ] && [ "$1" = "--" ]; then
    shift
fi
if [ $# -eq 0 ]; then
    set -- estimate --scale small --threads 1 --json
fi
field=${FIELD:-estimate_points_per_cpu_s}
for bin in "$a" "$b"; do
    [ -x "$bin" ] || { echo "ab-bench: $bin is not an executable" >&2; exit 2; }
done
case " $* " in
*" --json "*) ;;
*) echo "ab-bench: the bench arguments must include --json" >&2; exit 2 ;;
esac

figure() {
    # The bench prints one JSON object; pick the field's number out of it.
    "$1" bench "${@:2}" 2>/dev/null |
        tr -d ' \n' | grep -o "\"$field\":[-0-9.eE+]*" | head -n1 | cut -d: -f2
}

ratios=()
for ((i = 1; i <= pairs; i++)); do
    if ((i % 2 == 1)); then
        fa=$(figure "$a" "$@")
        fb=$(figure "$b" "$@")
    else
        fb=$(figure "$b" "$@")
        fa=$(figure "$a" "$@")
    fi
    if [ -z "$fa" ] || [ -z "$fb" ]; then
        echo "ab-bench: pair $i: no \"$field\" in the bench's output (run it by hand to see why)" >&2
        exit 1
    fi
    ratio=$(awk -v x="$fa" -v y="$fb" 'BEGIN { printf "%.4f", y / x }')
    echo "pair $i: A $fa  B $fb  B/A $ratio"
    ratios+=("$ratio")
done
printf '%s\n' "${ratios[@]}" | awk -v field="$field" '
    { l[NR] = log($1); s += l[NR] }
    END {
        n = NR; m = s / n
        for (i = 1; i <= n; i++) v += (l[i] - m) ^ 2
        # Two-sided 95 % quantiles of Student t for n − 1 degrees of freedom (1 … 10, then ~2).
        split("12.706 4.303 3.182 2.776 2.571 2.447 2.365 2.306 2.262 2.228", t, " ")
        q = (n - 1 <= 10) ? t[n - 1] : 2.0
        se = (n > 1) ? sqrt(v / (n - 1) / n) : 0
        if (n > 1)
            printf "%s, B/A: %.3f (95 %% interval %.3f … %.3f, %d pairs)\n", field, exp(m), exp(m - q * se), exp(m + q * se), n
        else
            printf "%s, B/A: %.3f (one pair: no interval)\n", field, exp(m)
    }'
