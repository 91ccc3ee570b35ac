#!/usr/bin/env bash
# Run a command under `strace -f` (every process it starts, --seccomp-bpf: only connect() and
# bind() stop it) and print how many of those calls left loopback (see docs/network.md for what
# counts). The last line of stdout is the count; the exit status is the command's, or 3 if it
# succeeded but something left loopback. Keep the whole log with TRACE_LOG=path.
#
#   bash benchmarks/trace_connects.sh python -m pytest -q            # the README's test command
#   bash benchmarks/trace_connects.sh kvtracker eval-many MANIFEST --engine ray --workers 2
set -euo pipefail
if [ "$#" -eq 0 ]; then
    echo "usage: bash benchmarks/trace_connects.sh COMMAND [ARGS...]" >&2
    exit 2
fi
root="$(cd "$(dirname "$0")/.." && pwd)"
python="${PYTHON:-python}"
log_args=()
if [ -n "${TRACE_LOG:-}" ]; then log_args=(--log "$TRACE_LOG"); fi
PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}" exec "$python" -m tests.network_trace \
    "${log_args[@]}" -- "$@"
