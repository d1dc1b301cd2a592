#!/usr/bin/env bash
# Build real Bifrost (ledatelescope/bifrost 0.10, a source tree you supply) with CUDA 12 or 13, to run
# this package's blocks inside it (docs/BIFROST_GPU.md says why each step is there). Checked with
# Bifrost c4828920 on an H100 with CUDA 13.0 and Python 3.12.
#
#   tools/build_bifrost_gpu.sh prepare BIFROST_SRC DEST
#       Copies the tree to DEST/src and answers Bifrost's one use of ctags (the list of function
#       prototypes of its public headers, for the library's export list) into DEST/bin, so the build
#       itself needs no ctags. Run it where ctags (exuberant or universal) is installed; DEST can then
#       be copied to a GPU machine that has none.
#   tools/build_bifrost_gpu.sh build DEST [PREFIX]        (default PREFIX: /tmp/bfgpu)
#       Applies the CUDA 13 changes to DEST/src, configures, builds libbifrost for the GPU's
#       architecture (GPU_ARCHS, default 90 = H100/H200), installs into PREFIX and installs the Python
#       package into python3. Needs nvcc (CUDA_HOME, default /usr/local/cuda), make, g++ and, in
#       python3, ctypesgen==1.0.2 (Bifrost generates its ctypes wrapper with it). Then:
#           export LD_LIBRARY_PATH=PREFIX/lib:$LD_LIBRARY_PATH
#       A PREFIX that already holds a working build is kept.
set -euo pipefail
cmd=${1:-}; shift || true
case "$cmd" in
prepare)
  SRC=${1:?usage: prepare BIFROST_SRC DEST}; DEST=${2:?usage: prepare BIFROST_SRC DEST}
  command -v ctags >/dev/null || { echo "prepare needs ctags (apt-get install universal-ctags)"; exit 1; }
  rm -rf "$DEST" && mkdir -p "$DEST/bin"
  cp -r "$SRC" "$DEST/src"
  (cd "$DEST/src/src" && ctags -x --c-kinds=p bifrost/*.h) > "$DEST/bin/ctags-protos.txt"
  # configure asks `ctags --version` for "Exuberant"; the Makefile asks for the prototype list
  cat > "$DEST/bin/ctags" <<'SH'
#!/bin/sh
case "$1" in --version) echo "Exuberant Ctags 5.8 (answers prepared by build_bifrost_gpu.sh)";;
*) cat "$(dirname "$0")/ctags-protos.txt";; esac
SH
  chmod +x "$DEST/bin/ctags"
  echo "prepared $DEST ($(wc -l < "$DEST/bin/ctags-protos.txt") prototypes); next: $0 build $DEST" ;;
build)
  DEST=$(cd "${1:?usage: build DEST [PREFIX]}" && pwd); PREFIX=${2:-/tmp/bfgpu}
  CUDA_HOME=${CUDA_HOME:-/usr/local/cuda}; ARCHS=${GPU_ARCHS:-90}
  export PATH=$DEST/bin:$PATH
  if [ -f "$PREFIX/lib/libbifrost.so" ] && LD_LIBRARY_PATH=$PREFIX/lib python3 -c "import bifrost" 2>/dev/null; then
    echo "Bifrost already built in $PREFIX"; exit 0
  fi
  cd "$DEST/src"
  # cuFFT 12 (CUDA 13) removed three result codes that Bifrost names in a switch
  python3 - <<'PY'
p = "src/fft_kernels.h"; s = open(p).read()
for n in ("CUFFT_INCOMPLETE_PARAMETER_LIST", "CUFFT_PARSE_ERROR", "CUFFT_LICENSE_ERROR"):
    old = f"\tDEFINE_CUFFT_RESULT_CASE({n});"
    if old in s and f"#if CUFFT_VERSION < 12000\n{old}" not in s:
        s = s.replace(old, f"#if CUFFT_VERSION < 12000\n{old}\n#endif")
open(p, "w").write(s)
PY
  # NVTX 3 is header-only (CUDA 12.9+ ships no libnvToolsExt)
  ls "$CUDA_HOME"/lib64/libnvToolsExt.so* >/dev/null 2>&1 || sed -i "s/ -lnvToolsExt//" configure
  # Thrust and CUB moved under include/cccl (CUDA 13)
  INC=""; [ -d "$CUDA_HOME/include/cccl" ] && INC="-I$CUDA_HOME/include/cccl"
  ./configure --prefix="$PREFIX" --with-python=python3 --with-cuda-home="$CUDA_HOME" --with-gpu-archs="$ARCHS" \
    --disable-hwloc CPPFLAGS="$INC" NVCCFLAGS="$INC" > "$DEST/configure.log" 2>&1 \
    || { tail -25 "$DEST/configure.log"; exit 1; }
  make -j"$(nproc)" > "$DEST/make.log" 2>&1 || { grep -n -i error "$DEST/make.log" | head -20; exit 1; }
  make install > "$DEST/install.log" 2>&1 || { tail -20 "$DEST/install.log"; exit 1; }
  mkdir -p "${HOME:-/tmp}"
  LD_LIBRARY_PATH=$PREFIX/lib python3 -m bifrost.telemetry --disable >/dev/null 2>&1 || true
  LD_LIBRARY_PATH=$PREFIX/lib python3 -c "import bifrost; from bifrost.ndarray import ndarray; \
print('bifrost', bifrost.__version__, 'cuda round trip:', ndarray([1, 2], dtype='f32', space='cuda').copy(space='system'))" ;;
*) sed -n 2,22p "$0"; exit 2 ;;
esac
