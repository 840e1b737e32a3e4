#!/usr/bin/env bash
# The checks that need a CUDA GPU, on a lent GPU machine (the device tool runs this in a copy of
# the repo; carry .whl with the OpenEXR wheel for its Python, see /work/.library/device/README.md):
#   bash scripts/gpu_check.sh
# Mitsuba and OIDN are absent there: tests that need them skip. Prints the GPU, then pytest's summary.
set -uo pipefail
if compgen -G ".whl/*.whl" > /dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())"
python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_ops_gather_splat.py tests/test_ops_importance.py \
  tests/test_ops_multiscale.py tests/test_model_kpcn.py tests/test_tiling.py 2>&1 | tail -25
