#!/bin/sh
# A Python 3.13 with bpy 5.x on this project's Debian 12 machines, for the Blender 5 recipe test
# (tests/test_blender_cycles.py::test_blender5_recipe; docs/DENOISE.md). bpy 5.x wheels need
# Python 3.13, which Debian 12 does not have: this unpacks Debian 13's (trixie) python3.13 and its
# libc into PREFIX without installing anything system-wide, runs it under trixie's own loader,
# and pip-installs bpy into PREFIX/site. Needs the Debian and PyPI mirrors only.
#
#   sh scripts/setup_bpy5.sh [PREFIX] [BPY_VERSION]     # default /opt/bpy5, 5.3.0
#   MCDENOISE_BLENDER5_PYTHON=/opt/bpy5/python pytest -m slow tests/test_blender_cycles.py -k blender5
set -eu
PREFIX=${1:-/opt/bpy5}
BPY=${2:-5.3.0}
mkdir -p "$PREFIX/apt/lists/partial" "$PREFIX/debs" "$PREFIX/root"
echo "deb http://deb.debian.org/debian trixie main" > "$PREFIX/apt/sources.list"
A="-o Dir::Etc::sourcelist=$PREFIX/apt/sources.list -o Dir::Etc::sourceparts=/dev/null -o Dir::State::Lists=$PREFIX/apt/lists"
apt-get $A update >/dev/null
cd "$PREFIX/debs"
apt-get $A download python3.13 python3.13-minimal libpython3.13-minimal libpython3.13-stdlib libpython3.13 \
  libc6 libssl3t64 libffi8 zlib1g libexpat1 libsqlite3-0 libbz2-1.0 liblzma5 libncursesw6 libtinfo6 \
  libreadline8t64 libuuid1 libgcc-s1 libstdc++6 libzstd1 libcrypt1 libmpdec4 python3-pip-whl >/dev/null
for d in *.deb; do dpkg -x "$d" "$PREFIX/root"; done
R="$PREFIX/root"
cat > "$PREFIX/python" <<PY
#!/bin/sh
# Debian 13's Python 3.13 under its own loader and libc; the host's libraries after its own.
PYTHONHOME=$R/usr PYTHONPATH=$PREFIX/site exec $R/usr/lib/x86_64-linux-gnu/ld-linux-x86-64.so.2 \\
  --library-path $R/usr/lib/x86_64-linux-gnu:$R/lib/x86_64-linux-gnu:/usr/lib/x86_64-linux-gnu:/lib/x86_64-linux-gnu \\
  $R/usr/bin/python3.13 "\$@"
PY
chmod +x "$PREFIX/python"
"$PREFIX/python" "$(ls "$R"/usr/share/python-wheels/pip-*.whl)/pip" install --no-cache-dir --target "$PREFIX/site" "bpy==$BPY"
"$PREFIX/python" -c "import bpy; print('bpy', bpy.app.version_string, 'in $PREFIX/python')"
