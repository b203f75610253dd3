# Sourced on a GPU machine that reaches no package registry, from the repository root, after
# benchmarks/gpu_bundle.sh built .whl and .gl elsewhere and they were carried here:
#   source benchmarks/gpu_env.sh && BUDGET=480 bash benchmarks/gpu_targets.sh
# Sets PY (the machine's python3), PYTHONPATH (the bundle's packages, then src) and the libraries' paths; where a
# .venv is here instead, it does nothing and gpu_targets.sh uses the venv.
if [ -d .venv ] || [ ! -f .whl/site.tar.xz ]; then
    echo "gpu_env.sh: a .venv is here or no .whl/site.tar.xz: nothing set" >&2
else
    _site=${WHITECAP_SITE:-/tmp/whitecap-site}
    if [ ! -f "$_site/.unpacked" ]; then
        mkdir -p "$_site" && tar -C "$_site" -xJf .whl/site.tar.xz && touch "$_site/.unpacked"
    fi
    # libX11 and kin into a folder of their own; the Vulkan loader and glvnd into / (GGUI looks for them there)
    mkdir -p /tmp/whitecap-libs
    for d in .gl/*.deb; do
        case "$(basename "$d")" in
            libvulkan1*|libglvnd0*|libegl1*|libopengl0*|libgl1*|libglx0*|libgles2*)
                if [ -w / ]; then dpkg -x "$d" / ; else dpkg -x "$d" /tmp/whitecap-libs; fi ;;
            *) dpkg -x "$d" /tmp/whitecap-libs ;;
        esac
    done
    [ -w / ] && command -v ldconfig >/dev/null && ldconfig
    _libs=$(find /tmp/whitecap-libs -name '*.so*' -printf '%h\n' | sort -u | paste -sd:)
    export LD_LIBRARY_PATH="/usr/local/nvidia/lib64:${_libs}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ] && \
        export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    export PYTHONPATH="$_site:$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
    export PY=python3
    unset _site _libs
fi
