"""A missing or unusable Vulkan driver gives an error that says what to run."""
import pytest

from stages.common import vulkan


def test_missing_driver_says_to_run_setup(monkeypatch, tmp_path):
    monkeypatch.delenv("VK_ICD_FILENAMES", raising=False)
    monkeypatch.setattr(vulkan, "ICD_FILE", tmp_path / "missing" / "lvp_icd.json")
    with pytest.raises(vulkan.VulkanUnavailable, match=r"bash scripts/setup\.sh"):
        vulkan.ensure_vulkan()


def test_user_icd_is_respected(monkeypatch, tmp_path):
    icd = tmp_path / "my_icd.json"
    icd.write_text("{}")
    monkeypatch.setenv("VK_ICD_FILENAMES", str(icd))
    assert vulkan.ensure_vulkan() == icd


def test_sapien_no_device_error_is_translated():
    with pytest.raises(vulkan.VulkanUnavailable, match="setup.sh"):
        vulkan.raise_if_no_device(RuntimeError("failed to find a rendering device"))
    vulkan.raise_if_no_device(RuntimeError("unrelated"))  # other errors pass through untouched
