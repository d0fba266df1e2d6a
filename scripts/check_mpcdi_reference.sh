#!/usr/bin/env bash
# ProCam's MPCDI files read back by the reference C++ MPCDI library (Scalable Display Technologies' MPCDI Library,
# BSD, the reader Unreal's nDisplay embeds), every value compared with what ProCam wrote.
#
# Usage: scripts/check_mpcdi_reference.sh [LIBRARY_GIT_URL] [WORK_DIR]
#   LIBRARY_GIT_URL  where to clone the library from (default https://github.com/scaredyfish/MPCDI.git; a local
#                    clone or mirror path works too)
#   WORK_DIR         where to clone, build and write the files (default: a new folder under /tmp); outside the
#                    repository — the library is never copied into it
#
# Needs git, g++, gcc, libpng and zlib headers (Debian: libpng-dev zlib1g-dev) and the repository's .venv
# (scripts/setup.sh). It clones the library, compiles its sources (src/*/*.cpp), its bundled tinyxml2 and minizip
# (from its bundled zlib's contrib) straight with g++/gcc against the system's libpng and zlib (the library's own
# CMake files are for CMake 2.4 and build bundled copies), links scripts/mpcdi_reference/read_mpcdi.cpp against
# them, then runs scripts/check_mpcdi_reference.py: exports with `procam export-mpcdi` (one and two projectors,
# profiles 2d and sl) and one file from ProCam's writer, each read by the library and compared. Exit 0: every value
# matches; 1: a mismatch or a file the library refused; 2: the library could not be fetched or built.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
url="${1:-https://github.com/scaredyfish/MPCDI.git}"
work="${2:-$(mktemp -d /tmp/mpcdi-reference.XXXXXX)}"
case "$(realpath -m "$work")/" in
  "$repo"/*) echo "WORK_DIR must lie outside the repository ($repo)" >&2; exit 2 ;;
esac
mkdir -p "$work"
src="$work/MPCDI" build="$work/build"

if [ ! -d "$src/.git" ]; then
  git clone --quiet --depth 1 "$url" "$src" || { echo "could not clone $url" >&2; exit 2; }
fi
echo "reference library: $url at $(git -C "$src" rev-parse --short HEAD) ($(git -C "$src" log -1 --format=%cs))"

mkdir -p "$build"
mz="$src/ThirdParty/zlib-1.2.7/contrib/minizip"
inc=(-I"$src/src/Base" -I"$src/src/IO" -I"$src/src/Container" -I"$src/src/Utils" -I"$src/src/Creators"
     -I"$src/ThirdParty/tinyxml2" -I"$mz")
objs=()
build_one() {  # compiler, source, object: compiled once
  [ -f "$3" ] || "$1" -O1 -w "${@:4}" -c "$2" -o "$3" || { echo "could not compile $2" >&2; exit 2; }
  objs+=("$3")
}
for f in ioapi unzip zip; do build_one gcc "$mz/$f.c" "$build/minizip_$f.o" -I"$mz"; done
build_one g++ "$src/ThirdParty/tinyxml2/tinyxml2.cpp" "$build/tinyxml2.o"
for f in "$src"/src/*/*.cpp; do
  build_one g++ "$f" "$build/mpcdi_$(basename "$f" .cpp).o" -std=c++11 "${inc[@]}"
done
g++ -std=c++11 -O1 -w "${inc[@]}" "$repo/scripts/mpcdi_reference/read_mpcdi.cpp" "${objs[@]}" -lpng -lz \
  -o "$build/read_mpcdi" || { echo "could not build the reader" >&2; exit 2; }
echo "reader: $build/read_mpcdi"

# The repository is the package `procam` (pyproject.toml); a link named procam puts it on the path.
mkdir -p "$work/py" && ln -sfn "$repo" "$work/py/procam"
rm -rf "$work/files"  # a rerun's exports start afresh
cd "$repo"
PYTHONPATH="$work/py" .venv/bin/python scripts/check_mpcdi_reference.py --reader "$build/read_mpcdi" \
  --work "$work/files"
