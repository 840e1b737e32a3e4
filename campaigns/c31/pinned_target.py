"""One-off probe of campaign 31 (docs/DATASETS.md, "Determinism"): run an mcdenoise command with Dr.Jit's
LLVM target forced, to ask whether the vector width is why two CPUs render different pixels.

    python campaigns/c31/pinned_target.py CPU FEATURES WIDTH mcdenoise-args...
    python campaigns/c31/pinned_target.py haswell +avx,+avx2,+fma,+f16c,+sse4.2,+popcnt,+bmi,+bmi2,+lzcnt,+movbe 8 \
        dataset --out /tmp/xt/detail_ref2 --count 1 --seed 197 ...   (the rest of campaigns/datasets.sh's recipe)

Dr.Jit 1.5 has no Python call for it, so this calls drjit-core's C++ ``jit_llvm_set_target`` through
ctypes after the variant is set and before the first kernel. Embree's kernels were forced separately, with
a file ``~/.embree3`` holding ``isa=avx2`` (Embree reads it when Mitsuba creates its device).
"""
import ctypes
import os
import sys

from mcdenoise.render._mitsuba import find_libllvm

os.environ.setdefault("DRJIT_LIBLLVM_PATH", find_libllvm() or "")
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_rgb")
core = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))
set_target = core._Z19jit_llvm_set_targetPKcS0_j  # jit_llvm_set_target(const char*, const char*, uint32_t)
set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
set_target(sys.argv[1].encode(), sys.argv[2].encode(), int(sys.argv[3]))
cpu = core._Z19jit_llvm_target_cpuv
cpu.restype = ctypes.c_char_p
width = core._Z21jit_llvm_vector_widthv
width.restype = ctypes.c_uint32
print(f"LLVM target {cpu().decode()}, {width()} lanes", file=sys.stderr)

from mcdenoise.cli.main import main  # noqa: E402

sys.exit(main(sys.argv[4:]))
