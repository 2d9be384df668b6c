#!/usr/bin/env bash
# Source at the start of every call on the lent GPU machine, after ../shared/device/stage-gpu.sh's install step:
# installs this package editable (offline) and links the real meshes, copied into the ignored .gpudata/meshes.
export PYTHONPATH=$HOME/site PYTHONUNBUFFERED=1 NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . > /tmp/pipe.log 2>&1 || cat /tmp/pipe.log
mkdir -p ../shared/data && ln -sfn "$PWD/.gpudata/meshes" ../shared/data/meshes
