import json, os, time
import pytest
T0 = float(os.environ.get("TL_T0", time.time()))
OUT = os.environ.get("TL_OUT", "/tmp/timeline.jsonl")

@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    s = time.time()
    c0 = time.process_time()
    yield
    e = time.time()
    with open(OUT, "a") as f:
        f.write(json.dumps({"w": os.environ.get("PYTEST_XDIST_WORKER", "m"), "id": item.nodeid,
                            "s": s - T0, "e": e - T0, "cpu": time.process_time() - c0}) + "\n")
