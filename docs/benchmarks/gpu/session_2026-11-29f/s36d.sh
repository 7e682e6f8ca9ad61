#!/bin/bash
export PYTHONUNBUFFERED=1
mkdir -p $OUT/rows
timeout -s INT 240 python3 .dev/s36d.py $OUT/rows 2>&1 | grep -v "Warning\|warn"
