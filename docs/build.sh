#!/usr/bin/env bash
# Build the documentation site: run every tutorial (each writes its figures into
# docs/tutorials/figures/ and asserts its own result, so a regression fails here), then build
# the site strictly (a broken link or cross-reference fails). Needs the docs and plot extras:
#   pip install -e ".[docs,plot]" && bash docs/build.sh
# Environment: PYTHON (default python), SITE_DIR (default site/, ignored by git). The figures
# always go to docs/tutorials/figures/ (ignored by git), the folder the pages show.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python}"
SITE_DIR="${SITE_DIR:-site}"
export MPLBACKEND=Agg
export DIFFCLOTH_FIGURES="$PWD/docs/tutorials/figures"
rm -rf "$DIFFCLOTH_FIGURES" && mkdir -p "$DIFFCLOTH_FIGURES"  # every figure from this run
tutorials=(simulate_and_render fit_material fit_footage drape_test)
total_start=$(date +%s.%N)
for name in "${tutorials[@]}"; do
  echo "== tutorial: docs/tutorials/${name}.py"
  start=$(date +%s.%N)
  "$PYTHON" "docs/tutorials/${name}.py"
  end=$(date +%s.%N)
  awk -v n="$name" -v a="$start" -v b="$end" 'BEGIN { printf "== tutorial %s: %.1f s\n", n, b - a }'
done
echo "== mkdocs build --strict --site-dir ${SITE_DIR}"
start=$(date +%s.%N)
"$PYTHON" -m mkdocs build --strict --site-dir "$SITE_DIR"
end=$(date +%s.%N)
awk -v a="$start" -v b="$end" 'BEGIN { printf "== mkdocs build: %.1f s\n", b - a }'
awk -v a="$total_start" -v b="$end" 'BEGIN { printf "== docs/build.sh: %.1f s in all\n", b - a }'
