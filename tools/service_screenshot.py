"""The service page's screenshot for the docs: a run with the service on, opened in headless Chromium.

    python tools/service_screenshot.py [PIPELINE.yaml] [--out docs/guide/img/service-page.png]

Runs the pipeline (default: the transient demo with its watchlist, made longer so the page has time
to show its PNGs), waits until the page shows two pictures and a candidate, and saves what the browser
draws.
"""
import argparse
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("yaml", nargs="?", default=str(REPO / "pipelines" / "lwasv_sim_transient.yaml"))
    ap.add_argument("--out", default=str(REPO / "docs" / "guide" / "img" / "service-page.png"))
    args = ap.parse_args(argv)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service as DriverService

    from bf_epic_blocks.pipeline import runner
    from bf_epic_blocks.pipeline.config import load_config
    out = tempfile.mkdtemp(prefix="service_page_")
    cfg = load_config(args.yaml, ["source.duration_s=1.5", "imager.grid.size=32", f"output.dir={out}",
                                  "watch.png_every_s=0.2", "service={listen: '127.0.0.1:0'}"])
    done = {}

    def shoot(srv):
        def go():
            opts = webdriver.ChromeOptions()
            opts.binary_location = shutil.which("chromium") or shutil.which("chromium-browser")
            for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=900,1600"):
                opts.add_argument(a)
            drv = webdriver.Chrome(service=DriverService(executable_path=shutil.which("chromedriver")), options=opts)
            try:
                t0 = time.monotonic()
                while (len(srv.pictures()) < 2 or not srv.snapshot().get("recent_candidates")) \
                        and time.monotonic() - t0 < 120:
                    time.sleep(0.5)
                drv.get(srv.url + "/")
                time.sleep(1.0)
                drv.save_screenshot(args.out)
                done["ok"] = True
            finally:
                drv.quit()
        threading.Thread(target=go, daemon=True).start()

    runner.run(cfg, show_progress=False, service_ready=shoot)
    print(f"wrote {args.out}" if done.get("ok") else "no screenshot: the run ended before the page had its pictures")
    return 0 if done.get("ok") else 1


if __name__ == "__main__":
    sys.exit(main())
