#!/bin/bash
# queue2.sh v1 v2 ...: nuts at defaults on the drift, one vehicle after another, until $UNTIL;
# a vehicle is claimed (claims/<v>) so two queues share one list.
cd /work/main
mkdir -p /work/runs/nutsdrift/claims
for v in "$@"; do
  mkdir /work/runs/nutsdrift/claims/$v 2>/dev/null || continue
  left=$(( $(date -d "$UNTIL" +%s) - $(date +%s) ))
  [ $left -lt 120 ] && break
  BAYESDRIVE_DATA_DIR=/work/shared/data timeout $left /work/venv/bin/python /work/runs/nutsdrift/one.py $v 20261219 > /work/runs/nutsdrift/v$v.log 2>&1
  echo "$v rc $? $(date)" >> /work/runs/nutsdrift/queue.log
done
