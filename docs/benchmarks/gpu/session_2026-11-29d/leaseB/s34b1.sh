#!/bin/bash
# session 34, lease B run 1: the 12 named scenes at head (the parts start's simplex past its cap while descending)
export PYTHONUNBUFFERED=1
OUT=$OUT/suite LIMIT=505 bash benchmarks/gpu_suite12.sh
