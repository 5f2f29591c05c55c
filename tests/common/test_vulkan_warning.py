"""ensure_vulkan silences SAPIEN's expected 'no system libvulkan' warning, and only that one."""
from __future__ import annotations

import warnings

from stages.common.vulkan import ensure_vulkan


def test_ensure_vulkan_silences_sapiens_libvulkan_fallback_warning(tmp_path, monkeypatch):
    icd = tmp_path / "icd.json"
    icd.write_text("{}")
    monkeypatch.setenv("VK_ICD_FILENAMES", str(icd))  # a user's driver: no .deps needed
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ensure_vulkan()
        warnings.warn("Failed to find system libvulkan. Fallback to SAPIEN builtin libvulkan.", UserWarning)
        warnings.warn("some other warning", UserWarning)
    assert [str(w.message) for w in caught] == ["some other warning"]
