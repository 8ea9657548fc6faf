#!/usr/bin/env bash
# A job on the lent machine that outlives its device call (each call runs at most 10 minutes; a process in a
# session of its own runs on until the machine goes back), and the later calls that follow it:
#   bash scripts/gpu/background.sh start NAME COMMAND...   starts COMMAND with setsid, its output in
#                                                          /root/bg/NAME.log, OUT=/root/bg/NAME for its files
#   bash scripts/gpu/background.sh wait NAME [SECONDS]     waits for it (default 540 s, inside one call's limit),
#                                                          prints the log's new lines, copies its files to $OUT
# `wait` exits 0 once the job has ended (its exit status in the log's last line), 3 while it still runs: call
# it again within 30 s (the machine stays warm that long after a call) until it has ended.
set -uo pipefail
verb=${1:-}; name=${2:-}
[[ ($verb == start || $verb == wait) && -n $name ]] || {
  echo "background.sh: usage: start NAME COMMAND... | wait NAME [SECONDS]" >&2; exit 2; }
bg=/root/bg; log=$bg/$name.log; mkdir -p "$bg/$name"
if [[ $verb == start ]]; then
  shift 2
  [[ $# -gt 0 ]] || { echo "background.sh: start $name: no command" >&2; exit 2; }
  [[ -f $bg/$name.pid ]] && kill -0 "$(cat "$bg/$name.pid")" 2>/dev/null && {
    echo "background.sh: $name is already running (pid $(cat "$bg/$name.pid"))" >&2; exit 2; }
  : >"$log"; echo 0 >"$bg/$name.shown"
  # stdin and stdout of the job are not the call's: the call returns at once
  OUT=$bg/$name setsid bash -c '"$@"; echo "== background job ended: exit $?"' job "$@" \
    >"$log" 2>&1 </dev/null &
  echo $! >"$bg/$name.pid"
  echo "background.sh: $name started (pid $!), log $log"
  exit 0
fi
[[ -f $log ]] || { echo "background.sh: no job $name (no $log)" >&2; exit 2; }
deadline=$((SECONDS + ${3:-540}))
shown=$(cat "$bg/$name.shown")
while :; do
  total=$(wc -l <"$log")
  ((total > shown)) && { sed -n "$((shown + 1)),${total}p" "$log"; shown=$total; }
  if grep -q "^== background job ended" "$log"; then break; fi
  ((SECONDS >= deadline)) && break
  sleep 5
done
echo "$shown" >"$bg/$name.shown"
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
cp -r "$bg/$name/." "$OUT/" 2>/dev/null || true
grep -q "^== background job ended" "$log" && exit 0
echo "background.sh: $name still runs; call wait again"; exit 3
