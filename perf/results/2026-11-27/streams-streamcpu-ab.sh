#!/usr/bin/env bash
# A/B of the stream reader's CPU (branch streamcpu) against its base, alternating, with perf/streams
# (--brokers leveret --messages 2000000: publish-consume of 2M x 16 B, then a cold read of 1 GiB,
# 1M x 1 KiB, page cache dropped). Both binaries are release builds (fat LTO) kept outside the tree:
#   A = 75f53d0 (base), B = a streamcpu build (ab55326 for rounds 1-8; the commit after it, "fix", for 9-12,
#   run with labels streamcpu2-{base,branch2}-rN and B first in the even rounds).
# usage: perf/results/2026-11-27/streams-streamcpu-ab.sh A_DIR B_DIR ROUNDS
# Output: perf/streams' files (named by the worktree's HEAD and the label), renamed afterwards to
# streams-streamcpu-ab-{base,branch}-rN.txt with a first line naming the binary.
set -euo pipefail
here=$(cd "$(dirname "$0")/../.." && pwd)
a=$1 b=$2 rounds=${3:-3}
for r in $(seq 1 "$rounds"); do
  T=$a "$here/streams" --brokers leveret --messages 2000000 --label "streamcpu-base-r$r"
  T=$b "$here/streams" --brokers leveret --messages 2000000 --label "streamcpu-branch-r$r"
done
