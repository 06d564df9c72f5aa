"""The page tests' gate: without a browser they skip with a one-line reason, except under CI,
where a missing browser fails them (CI must run them; .ci/run installs Chromium)."""

import pytest
import webdriver


@pytest.mark.parametrize(
    "ci, outcome", [("true", "fail"), ("1", "fail"), ("", "skip"), ("false", "skip"), (None, "skip")]
)
def test_a_missing_browser_skips_outside_ci_and_fails_under_ci(monkeypatch, ci, outcome):
    monkeypatch.setattr(webdriver, "CHROMIUM", "/nonexistent/chromium")
    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    ran = []
    test = webdriver.needs_chromium(lambda: ran.append(1))
    expected = pytest.fail.Exception if outcome == "fail" else pytest.skip.Exception
    with pytest.raises(expected, match="apt-get install chromium chromium-driver") as info:
        test()
    assert not ran and "\n" not in str(info.value) and "/nonexistent/chromium" in str(info.value)


def test_an_installed_browser_runs_the_test(monkeypatch, tmp_path):
    fake = tmp_path / "chromium"
    fake.write_text("#!/bin/sh\n")
    fake.chmod(0o755)
    monkeypatch.setattr(webdriver, "CHROMIUM", str(fake))
    monkeypatch.setattr(webdriver, "CHROMEDRIVER", str(fake))
    monkeypatch.setenv("CI", "true")
    assert webdriver.needs_chromium(lambda x: x + 1)(1) == 2
