#!/bin/bash
export PYTHONUNBUFFERED=1
mkdir -p $OUT/rows
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
timeout -s INT 545 python3 .dev/s36c.py $OUT/rows 2>&1 | grep -v "Warning\|warn"
