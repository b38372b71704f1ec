#!/bin/bash
# ../shared/tools/real_check.py through a tiled map: its CLI, with `build ... --out MAP` made
# `build ... --tiles MAP --side $SIDE` (default 50 m); `query MAP` then reads the tiled map.
#   SIDE=10 .venv/bin/python ../shared/tools/real_check.py --cli tools/real_check_tiled.sh
# (from the repository root; docs/results.md, "A real sweep through tiles").
here="$(cd "$(dirname "$0")/.." && pwd)"
cli="$here/.venv/bin/uncertain-facade-map"
if [ "$1" = build ]; then
  args=()
  for a in "$@"; do if [ "$a" = --out ]; then args+=(--tiles); else args+=("$a"); fi; done
  exec "$cli" "${args[@]}" --side "${SIDE:-50}" --quiet
fi
exec "$cli" "$@"
