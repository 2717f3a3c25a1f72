"""The live page of `tagdeflect demo --c1609` in headless Chromium, for docs/demo-c1609-live.png.

usage: demo_live_screenshot.py URL TOKEN_FILE OUT_PNG [TIMEOUT_S]

Waits for the demo's automatic test to run, marks "first crack seen" once the page has drawn
the first peak P1 (the operator's mark, with the token the daemon wrote), waits for the
automatic stop, the verdict and the report's link, and saves the page (the test panel and the
live curve with L/600, L/150, P1 and the marks). Prints one JSON object with what it saw.
Run it beside `tagdeflect demo --c1609 DIR --small --http ADDR` (TOKEN_FILE is DIR/tests/.token).
Uses the tests' Chromium helper (tests/fixtures/browser.py; selenium from scripts/test.sh's venv).
"""

import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests" / "fixtures"))
from selenium.webdriver.common.by import By  # noqa: E402

from browser import chromium, close, wait_for  # noqa: E402

url, token_file, png = sys.argv[1:4]
timeout_s = float(sys.argv[4]) if len(sys.argv) > 4 else 3600
driver, profile = chromium(prompts_ignored=True)
out = {}


def text(id_):
    return driver.find_element(By.ID, id_).text


def data(id_, key):
    return driver.find_element(By.ID, id_).get_attribute("data-" + key)


try:
    t0 = time.time()
    while True:
        try:
            driver.get(url)
            break
        except Exception:
            if time.time() - t0 > timeout_s:
                raise
            time.sleep(5)
    out["running"] = wait_for("the test runs", lambda: text("t-state").startswith("running") and text("t-state"), timeout_s, out)
    token = pathlib.Path(token_file).read_text().split()[0]
    driver.execute_script("sessionStorage.setItem('tagdeflect-token', arguments[0])", token)
    out["p1"] = wait_for("P1 drawn", lambda: data("curve", "p1"), timeout_s, out)
    driver.find_element(By.ID, "b-mark").click()
    alert = wait_for("the note's prompt", lambda: driver.switch_to.alert, 10, out)
    alert.send_keys("first crack seen")
    alert.accept()
    wait_for("mark done", lambda: text("t-message") == "mark done", 30, out)
    out["verdict"] = wait_for("the verdict", lambda: data("t-verdict", "verdict") in ("valid", "invalid", "no-report")
                              and data("t-verdict", "verdict"), timeout_s, out)
    out["verdict_text"] = text("t-verdict")
    out["links"] = driver.execute_script("return [...document.querySelectorAll('#t-report-links a')].map(a => a.href)")
    out["lines"] = data("curve", "lines")
    out["marks"] = data("curve", "marks")
    time.sleep(3)
    driver.execute_script("document.getElementById('test-panel').scrollIntoView()")
    driver.save_screenshot(png)
except Exception as e:
    out.setdefault("error", repr(e))
finally:
    close(driver, profile)
print(json.dumps(out))
