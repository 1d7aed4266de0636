"""The labelling page's states as docs/label_page*.png: a walker-walk session of random-action episodes rendered
with osmesa, in headless Chromium at 800 x 600 (Debian's chromium and chromium-driver, selenium).

    MUJOCO_GL=osmesa python benchmarks/label_page_screenshots.py [--out docs]
"""

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import label_server  # noqa: E402
import sim_teacher  # noqa: E402


def wait(condition, timeout=300):
    deadline = time.time() + timeout
    while not condition():
        if time.time() > deadline:
            raise TimeoutError("the page did not reach the state")
        time.sleep(0.2)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs")
    out = Path(parser.parse_args().out)
    from selenium import webdriver
    from selenium.webdriver.common.action_chains import ActionChains

    run = Path(tempfile.mkdtemp()) / "run"
    (run / "queries").mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"env_id": "walker-walk", "segment_len": 50, "seed": 1}))
    rng = np.random.default_rng(0)
    arrays = {"step": np.int64(20001)}
    for side in (0, 1):
        arrays |= {f"seed{side}": rng.integers(0, 2**31, 2).astype(np.int64),
                   f"start{side}": rng.integers(0, 200, 2).astype(np.int64),
                   f"actions{side}": rng.uniform(-1, 1, (2, 260, 6)).astype(np.float32)}
    np.savez(run / "queries" / "session_0000.npz", **arrays)
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium") or shutil.which("chromium-browser") or ""
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=webdriver.ChromeService(shutil.which("chromedriver")))
    driver.set_window_size(800, 600)
    server = label_server.serve(str(run), "127.0.0.1", 0)
    keys = lambda text: ActionChains(driver).send_keys(text).perform()  # noqa: E731
    ready = lambda: driver.find_element("css selector", "button[data-label=left]").is_enabled()  # noqa: E731
    message = lambda: driver.find_element("id", "message").text  # noqa: E731
    waiting = lambda: driver.find_element("id", "waiting").text  # noqa: E731
    try:
        driver.get(server.url)
        wait(ready)
        time.sleep(1.0)
        driver.save_screenshot(str(out / "label_page.png"))
        keys("p")
        keys("h")
        keys(".")
        time.sleep(0.3)
        driver.save_screenshot(str(out / "label_page_paused.png"))
        keys("p")
        answers = {"order": [0], "answers": {"0": "equal"}}  # another browser answers pair 0 meanwhile
        sim_teacher.write_answers(str(run), 0, answers)
        keys("1")
        wait(lambda: "another browser" in message() and ready())
        driver.save_screenshot(str(out / "label_page_other_browser.png"))
        keys("2")
        wait(lambda: waiting().startswith("Session 0"))
        driver.save_screenshot(str(out / "label_page_session_done.png"))
        (run / "final_model.pt").write_bytes(b"")
        wait(lambda: waiting().startswith("The run has finished"))
        driver.save_screenshot(str(out / "label_page_run_finished.png"))
    finally:
        server.close()
        driver.quit()
    print(f"screenshots in {out}")


if __name__ == "__main__":
    main()
