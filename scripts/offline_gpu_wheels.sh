#!/usr/bin/env bash
# Rebuild .whl/: an offline wheel bundle for the lent GPU (device) machines.
#
# Why: the lent GPU machines have no network and their image lacks kornia, pypose and
# open3d (plus some system libraries open3d links against). The working tree sent there
# is limited to 64 MiB, so this bundle must stay <= 45 MiB. It holds cp312 wheels of
# kornia 0.9.0, pypose 0.9.5, kornia_rs 0.2.0 (.so stripped, repacked) and open3d-cpu
# 0.20.0 (ML ops/resources/jupyter/web removed, plotly/dash imports made optional,
# METADATA requirements trimmed, LZMA-repacked, RECORD regenerated), lib/ with the system
# libraries libOpen3D.so needs (Debian 12 builds), and setup.sh that installs it all.
# .whl/ is git-ignored: rerun this script in each new session that needs it.
#
# Usage:  bash scripts/offline_gpu_wheels.sh [OUT_DIR]      (default: <repo>/.whl)
#   then call the device with carry [".whl"] and a command beginning
#   source .whl/setup.sh && python3 -m pytest -q -k "cuda or gpu" tests
# Needs: python3 + pip reaching PyPI, strip (binutils), apt-get/dpkg (Debian 12), 3-10 min
# (LZMA of the 228 MB libOpen3D.so dominates). LIBS_FROM_APT=1 forces apt-get download
# of all system libraries instead of copying the host's copies.
set -euo pipefail

die() { echo "offline_gpu_wheels.sh: ERROR: $*" >&2; exit 1; }
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="$(realpath -m "${1:-$REPO/.whl}")"
case "$OUT" in /|"$REPO"|"$HOME"|/tmp) die "refusing to replace $OUT";; esac
if [ -d "$OUT" ] && [ -n "$(ls -A "$OUT")" ] && ! ls "$OUT"/setup.sh "$OUT"/*.whl >/dev/null 2>&1; then
    die "$OUT is a non-empty folder that does not look like a wheel bundle; refusing to replace it"
fi
command -v strip >/dev/null || die "'strip' not found (apt-get install -y binutils)"

WORK="$(mktemp -d)"; STAGE="$WORK/out"   # built here, moved to OUT_DIR only when complete
trap 'rm -rf "$WORK"' EXIT
mkdir -p "$STAGE/lib" "$WORK/dl"

# --- 1. the four original wheels from PyPI, checked against the hashes of the earlier build
echo "== downloading wheels"
pipdl() { nice -n 19 python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
              --implementation cp --abi cp312 -d "$WORK/dl" "$@" \
          || die "pip download failed: $* (network/PyPI reachable?)"; }
pipdl --platform manylinux_2_35_x86_64 open3d-cpu==0.20.0 kornia==0.9.0 pypose==0.9.5
pipdl --platform manylinux_2_17_x86_64 kornia_rs==0.2.0
O3D=open3d_cpu-0.20.0-cp312-cp312-manylinux_2_35_x86_64.whl
KRS=kornia_rs-0.2.0-cp312-cp312-manylinux_2_17_x86_64.manylinux2014_x86_64.whl
(cd "$WORK/dl" && sha256sum -c --quiet) <<EOF2 || die "downloaded wheels differ from the expected ones"
cee9c7686a794de792070f029f8b81913aff1269154ee43de9cc4af72fa5e087  $O3D
a5ccc43e7b54a845c4250dee107b62d221b4a76f6812a8041196784f4add342a  $KRS
7a1632fe004a305c94f2b979fc6ab4df26e01f925e74bdb9f8b8a03a1229caaf  kornia-0.9.0-py3-none-any.whl
ba9e8babbf5b54b1d54168fb030458d8ef84e66f7d5d013d5263eec27b70bed1  pypose-0.9.5-py3-none-any.whl
EOF2
cp "$WORK"/dl/kornia-0.9.0-py3-none-any.whl "$WORK"/dl/pypose-0.9.5-py3-none-any.whl "$STAGE"/

# --- 2. slim + repack open3d-cpu and kornia_rs (stdlib only). Deterministic: sorted entries,
# fixed timestamps, files > 256 KiB LZMA (preset 9e, zip method 14), the rest deflate-9.
echo "== repacking $O3D and $KRS (LZMA, several minutes)"
nice -n 19 python3 - "$WORK/dl" "$STAGE" "$O3D" "$KRS" <<'PY' || die "repacking failed"
import base64, hashlib, lzma, os, re, struct, subprocess, sys, tempfile, zipfile
dl, out, o3d, krs = sys.argv[1:]

class LZMA9e(zipfile.LZMACompressor):  # stdlib zip LZMA uses preset 6; use 9 | extreme
    def _init(self):
        filt = {'id': lzma.FILTER_LZMA1, 'preset': 9 | lzma.PRESET_EXTREME}
        props = lzma._encode_filter_properties(filt)
        self._comp = lzma.LZMACompressor(lzma.FORMAT_RAW, filters=[filt])
        return struct.pack('<BBH', 9, 4, len(props)) + props
zipfile.LZMACompressor = LZMA9e

def repack(name, drop=(), edit=lambda n, d: d):
    zin = zipfile.ZipFile(os.path.join(dl, name))
    infos = {i.filename: i for i in zin.infolist() if not i.filename.endswith(('/', '.dist-info/RECORD'))
             and not any(i.filename == p or i.filename.startswith(p + '/') for p in drop)}
    distinfo = next(n.split('/')[0] for n in infos if n.split('/')[0].endswith('.dist-info'))
    record, lines = distinfo + '/RECORD', []
    with zipfile.ZipFile(os.path.join(out, name), 'w', allowZip64=True) as z:
        for f in sorted(infos, key=lambda f: (f.startswith(distinfo), f)):  # dist-info last
            data = edit(f, zin.read(f))
            h = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b'=').decode()
            lines.append(f'{f},sha256={h},{len(data)}')
            zi = zipfile.ZipInfo(f, date_time=(2020, 1, 1, 0, 0, 0))
            zi.external_attr = ((0o755 if (infos[f].external_attr >> 16) & 0o111 else 0o644) | 0o100000) << 16
            zi.compress_type = zipfile.ZIP_LZMA if len(data) > 256 * 1024 else zipfile.ZIP_DEFLATED
            z.writestr(zi, data, compresslevel=9 if zi.compress_type == zipfile.ZIP_DEFLATED else None)
        lines.append(f'{record},,')
        zi = zipfile.ZipInfo(record, date_time=(2020, 1, 1, 0, 0, 0))
        zi.external_attr = 0o100644 << 16
        z.writestr(zi, '\n'.join(lines) + '\n', compress_type=zipfile.ZIP_DEFLATED)
    print(f'   {name}: {len(infos)} files, {os.path.getsize(os.path.join(out, name))} bytes', flush=True)

def sub(data, old, new, count):  # exact text edit that must apply `count` times
    s, n = re.subn(old, new, data.decode())
    assert n == count, (old, n)
    return s.encode()

def edit_o3d(f, d):
    if f == 'open3d/_build_config.py':  # the removed ops/extensions are reported as absent
        return sub(d, r'("(?:BUILD_TENSORFLOW_OPS|BUILD_PYTORCH_OPS|BUILD_JUPYTER_EXTENSION|BUNDLE_OPEN3D_ML)" : )True',
                   r'\1False', 4)
    if f == 'open3d/visualization/__init__.py':  # plotly/dash are not installed
        return sub(d, r'((?:from \.draw_plotly import \w+\n){3})',
                   lambda m: 'try:  # slimmed wheel: plotly/dash are optional\n'
                   + ''.join('    ' + l + '\n' for l in m.group(1).splitlines())
                   + 'except ImportError:\n    pass\n', 1)
    if f.endswith('.dist-info/METADATA'):
        return sub(d, r'Requires-Dist: (?:dash|werkzeug|flask|nbformat|configargparse|ipywidgets)\b[^\n]*\n', '', 6)
    return d

def edit_krs(f, d):
    if not f.endswith('.so'):
        return d
    with tempfile.NamedTemporaryFile(suffix='.so') as t:
        t.write(d); t.flush()
        subprocess.run(['strip', '-s', t.name], check=True)
        return open(t.name, 'rb').read()

repack(krs, edit=edit_krs)
repack(o3d, edit=edit_o3d, drop=[
    'open3d/' + p for p in ('_ml3d', 'agent_skills', 'examples', 'labextension', 'nbextension', 'resources',
                            'tools', 'ml/tf', 'ml/torch', 'visualization/tensorboard_plugin', 'app.py',
                            'web_visualizer.py', 'open3d_tf_ops.so', 'open3d_torch_ops.so')]
    + ['open3d_cpu-0.20.0.data', 'open3d_cpu-0.20.0.dist-info/entry_points.txt'])
for name in (o3d, krs):
    assert zipfile.ZipFile(os.path.join(out, name)).testzip() is None, name
PY
(cd "$STAGE" && sha256sum -c --quiet 2>/dev/null) <<EOF2 && echo "   repacked wheels are byte-identical to the reference build" \
  || echo "   note: repacked wheels differ from the reference build (other liblzma/strip version?)"
42b90756689ef8b070349361ef97ba2afe85afc3f2622b5ba0457a749e126651  $O3D
38e9d3e0466695eccc90ff63cebdc7da9aa62a80a742a699bf3bbd429e89b1ee  $KRS
EOF2

# --- 3. system libraries libOpen3D.so needs (linked BIND_NOW) that the device image may lack.
# The host's copy is used when present (Debian 12 builds), else the package is fetched with
# apt-get download and unpacked with dpkg -x.
echo "== system libraries -> lib/"
LIBS="libusb-1.0-0:libusb-1.0.so.0 libgl1:libGL.so.1 libglx0:libGLX.so.0 libglvnd0:libGLdispatch.so.0
      libegl1:libEGL.so.1 libx11-6:libX11.so.6 libxcb1:libxcb.so.1 libxau6:libXau.so.6
      libxdmcp6:libXdmcp.so.6 libbsd0:libbsd.so.0 libmd0:libmd.so.0 libudev1:libudev.so.1"
missing=()
for pl in $LIBS; do
    so="${pl#*:}"; sys="/usr/lib/x86_64-linux-gnu/$so"
    if [ "${LIBS_FROM_APT:-0}" != 1 ] && [ -e "$sys" ]; then cp -L "$sys" "$STAGE/lib/$so"; else missing+=("${pl%%:*}"); fi
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "   apt-get download ${missing[*]}"
    mkdir -p "$WORK/deb"
    (cd "$WORK/deb" && { apt-get download -q "${missing[@]}" >/dev/null 2>&1 \
        || { apt-get update -qq && apt-get download -q "${missing[@]}"; }; }) \
      || die "apt-get download ${missing[*]} failed"
    for deb in "$WORK"/deb/*.deb; do dpkg -x "$deb" "$WORK/root"; done
    for pl in $LIBS; do
        so="${pl#*:}"; [ -e "$STAGE/lib/$so" ] && continue
        f="$(find "$WORK/root" -name "$so" | head -n1)"
        [ -n "$f" ] || die "$so not found in the downloaded packages"
        cp -L "$f" "$STAGE/lib/$so"
    done
fi
chmod 644 "$STAGE"/lib/*

# --- 4. setup.sh, sourced on the device (same text as the one used on the H100 run)
cat > "$STAGE/setup.sh" <<'SETUP'
# Source from the repository root on the offline device:   source .whl/setup.sh
# Installs the bundled wheels (kornia, kornia_rs, pypose, slimmed open3d-cpu) into
# /tmp/site, puts them and the repo on PYTHONPATH, and makes the bundled system
# libraries (.whl/lib) visible to the loader for those the image lacks.
# Override the interpreter with PY=/path/to/python3 if needed.
_o3d_py="${PY:-python3}"
_o3d_root="$PWD"
"$_o3d_py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site "$_o3d_root"/.whl/*.whl \
  && export PYTHONPATH="/tmp/site:$_o3d_root${PYTHONPATH:+:$PYTHONPATH}" \
  || { echo "setup.sh: pip install of .whl/*.whl failed" >&2; return 1 2>/dev/null || exit 1; }

# System libraries needed by open3d/libOpen3D.so (linked BIND_NOW, so all must load).
# Only those the image's loader cache does not already know are exposed, so that
# the image's own copies (e.g. libudev, libGL) keep precedence where present.
_o3d_ldc="$(command -v ldconfig || echo /sbin/ldconfig)"
if "$_o3d_ldc" -p >/dev/null 2>&1; then
    rm -rf /tmp/o3d_syslib && mkdir -p /tmp/o3d_syslib
    for _o3d_l in "$_o3d_root"/.whl/lib/*.so*; do
        _o3d_n="$(basename "$_o3d_l")"
        "$_o3d_ldc" -p | grep -q "^[[:space:]]*$_o3d_n (.*x86-64" \
            || ln -sf "$_o3d_l" /tmp/o3d_syslib/"$_o3d_n"
    done
    echo "setup.sh: bundled system libs used: $(ls /tmp/o3d_syslib | tr '\n' ' ')"
    export LD_LIBRARY_PATH="/tmp/o3d_syslib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
else
    export LD_LIBRARY_PATH="$_o3d_root/.whl/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
fi
unset _o3d_ldc _o3d_l _o3d_n

"$_o3d_py" -c "
import open3d, kornia, kornia_rs, pypose, torch, numpy, tactile_slam
print('open3d', open3d.__version__, '| kornia', kornia.__version__, '| kornia_rs', kornia_rs.__version__,
      '| pypose', pypose.__version__, '| torch', torch.__version__, '| numpy', numpy.__version__)
m = open3d.geometry.TriangleMesh.create_sphere(); print(m)
" || { echo "setup.sh: import check failed" >&2; unset _o3d_py _o3d_root; return 1 2>/dev/null || exit 1; }
unset _o3d_py _o3d_root
SETUP

# --- 5. size check, then replace OUT_DIR's contents
LIMIT=$((45 * 1024 * 1024))
size=$(du -sb "$STAGE" | cut -f1)
[ "$size" -le "$LIMIT" ] || die "bundle is $size bytes > 45 MiB ($LIMIT); not installed to $OUT"
rm -rf "$OUT" && mv "$STAGE" "$OUT"
ls -l "$OUT"; ls "$OUT/lib" | tr '\n' ' '; echo
awk -v s="$size" -v o="$OUT" 'BEGIN { printf "== %s: %d bytes = %.2f MiB (limit 45 MiB)\n", o, s, s / 1048576 }'
