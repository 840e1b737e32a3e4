#!/usr/bin/env bash
# Build .gpu/site_mi.tar.xz and .gpu/site_dr.tar.xz: Mitsuba 3.9.1, Dr.Jit 1.5.0 and OpenEXR 3.5.3
# for the GPU machine's Python 3.12, unpacked from their PyPI wheels and slimmed to what the RGB
# variants need, so that they travel with the device tool (64 MiB per call; the whole mitsuba wheel
# is 63 MB). scripts/gpu_campaign.sh unpacks them into /tmp/site there.
#
#   bash scripts/gpu_site.sh        # needs pip and PyPI; writes .gpu/ (ignored via .git/info/exclude)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
work=$(mktemp -d); trap 'rm -rf "$work"' EXIT
$PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 -d "$work/whl" mitsuba==3.9.1 drjit==1.5.0 OpenEXR==3.5.3
mkdir -p "$work/mi" "$work/dr" .gpu
unzip -q "$work"/whl/mitsuba-*.whl -d "$work/mi"
(cd "$work/mi/mitsuba" &&
  # Only cuda_ad_rgb (and scalar_rgb/llvm_ad_rgb, small) are used; spectral upsampling data, C++
  # headers, CMake files and type stubs are not needed at run time.
  rm -f cuda_ad_mono* cuda_ad_spectral* llvm_ad_mono* llvm_ad_spectral* data/srgb.coeff libIlmImfUtil-mitsuba.so &&
  rm -rf include cmake mitsuba_stubs pkgconfig && find . -name '*.pyi' -delete)
for w in "$work"/whl/drjit-*.whl "$work"/whl/openexr-*.whl; do unzip -q -o "$w" -d "$work/dr"; done
tar -C "$work/mi" -cJf .gpu/site_mi.tar.xz .
tar -C "$work/dr" -cJf .gpu/site_dr.tar.xz .
grep -qx '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
ls -la .gpu
