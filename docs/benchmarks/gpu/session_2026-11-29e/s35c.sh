#!/bin/bash
export PYTHONUNBUFFERED=1
mkdir -p $OUT/rows
python3 .dev/s35c.py $OUT/rows 2>&1 | grep -v "Warning\|warn"
