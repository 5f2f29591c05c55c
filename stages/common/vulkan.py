"""Point SAPIEN at the project's software Vulkan driver before it is imported.

SAPIEN needs a Vulkan device even for state-only physics; on CPU machines that is Mesa's
lavapipe, fetched by ``bash scripts/setup.sh`` into ``.deps/vulkan`` (see docs/collect.md).
"""
from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
ICD_FILE = REPO_ROOT / ".deps" / "vulkan" / "lvp_icd.json"
_SETUP_HINT = "run `bash scripts/setup.sh` from the repository root to install it"


class VulkanUnavailable(RuntimeError):
    """No usable Vulkan driver for SAPIEN."""


def ensure_vulkan() -> Path:
    """Set ``VK_ICD_FILENAMES`` to the project's lavapipe ICD file and return that path.

    A user-set ``VK_ICD_FILENAMES`` pointing at an existing file is respected. Must run before
    ``sapien`` is imported, since the Vulkan loader reads the variable once.
    """
    # Without a system libvulkan.so.1 SAPIEN warns on import and loads its bundled loader, which is
    # the intended set-up here (the ICD below is the driver); the warning only cluttered every log.
    warnings.filterwarnings("ignore", message="Failed to find system libvulkan", category=UserWarning)
    user = os.environ.get("VK_ICD_FILENAMES")
    if user and all(Path(p).is_file() for p in user.split(os.pathsep)):
        return Path(user.split(os.pathsep)[0])
    if not ICD_FILE.is_file():
        raise VulkanUnavailable(f"software Vulkan driver not found at {ICD_FILE}; {_SETUP_HINT}")
    if "sapien" in sys.modules and os.environ.get("VK_ICD_FILENAMES") != str(ICD_FILE):
        raise VulkanUnavailable(
            "sapien was imported before stages.common.vulkan.ensure_vulkan(); call it first "
            "(the Vulkan loader reads VK_ICD_FILENAMES only once)"
        )
    os.environ["VK_ICD_FILENAMES"] = str(ICD_FILE)
    os.environ.setdefault("LP_NUM_THREADS", "1")  # lavapipe's own threads fight the workers on 2 cores
    return ICD_FILE


def raise_if_no_device(err: BaseException) -> None:
    """Re-raise SAPIEN's 'failed to find a rendering device' as an error that says what to do."""
    if "rendering device" in str(err) or "vulkan" in str(err).lower():
        raise VulkanUnavailable(
            f"SAPIEN found no Vulkan device ({err}); VK_ICD_FILENAMES={os.environ.get('VK_ICD_FILENAMES')!r}; "
            f"{_SETUP_HINT}"
        ) from err
