"""Is there a Vulkan device for GGUI? Checked before any window is made.

GGUI draws through Vulkan. Without a GPU, Mesa's lavapipe (Debian packages
``mesa-vulkan-drivers`` and ``libvulkan1``) provides a software device.
Creating a window with no loader or driver can crash the process, so the
loader library and the ICD manifests are looked for first.
"""

from __future__ import annotations

import ctypes.util
import glob
import os

from ..errors import WhitecapError

INSTALL_HINT = (
    "no Vulkan device for the viewer: install Vulkan (Debian/Ubuntu: "
    "sudo apt-get install mesa-vulkan-drivers libvulkan1) or a GPU driver with Vulkan support"
)

_ICD_DIRS = ("/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d", "/usr/local/share/vulkan/icd.d")


def vulkan_problem() -> str | None:
    """None when a loader and at least one driver manifest exist, else what is missing."""
    if os.environ.get("WHITECAP_FAKE_NO_VULKAN"):  # lets tests check the message
        return "Vulkan disabled by WHITECAP_FAKE_NO_VULKAN"
    if not (ctypes.util.find_library("vulkan") or glob.glob("/usr/lib/*/libvulkan.so.1")
            or glob.glob("/usr/lib/libvulkan.so.1")):
        return "the Vulkan loader libvulkan.so.1 is missing"
    icds = [f for d in _ICD_DIRS for f in glob.glob(os.path.join(d, "*.json"))]
    if os.environ.get("VK_ICD_FILENAMES") or os.environ.get("VK_DRIVER_FILES"):
        return None
    if not icds:
        return "no Vulkan driver manifest (ICD json) found"
    return None


def require_vulkan() -> None:
    why = vulkan_problem()
    if why:
        raise WhitecapError(f"{INSTALL_HINT} ({why})")
