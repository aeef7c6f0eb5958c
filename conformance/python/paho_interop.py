"""Runs one file of Eclipse Paho's MQTT interoperability suite
(eclipse/paho.mqtt.testing, `interoperability/client_test.py` for MQTT
3.1.1, `client_test5.py` for 5.0) against a broker, unchanged:

    python paho_interop.py --dir SUITE/interoperability --file client_test5.py --port PORT
        [--exclude TEST,...] [TEST ...]

The suite's own `__main__` block runs (it sets the topics, host and port
from its options); only `unittest.main` is replaced, so that the tests run
with a result that prints one JSON line per test: {"test", "status",
"detail"}, status pass / fail / skip. Tests are named as unittest names
them (`test_basic`); with names given, only those run.
"""

import argparse
import io
import json
import os
import runpy
import sys
import time
import traceback
import unittest


class JsonResult(unittest.TestResult):
    """Prints each test's outcome as it ends (a run cut short by a hang
    keeps what finished)."""

    @staticmethod
    def name(test):
        # A failing setUpClass is reported on a holder without a method name.
        return getattr(test, "_testMethodName", None) or str(test).split(" ")[0]

    def startTest(self, test):
        super().startTest(test)
        self._t0 = time.monotonic()
        print(json.dumps({"start": self.name(test)}), file=sys.__stdout__, flush=True)

    def _emit(self, test, status, detail=""):
        print(json.dumps({"test": self.name(test), "status": status, "detail": detail[-1500:],
                          "s": round(time.monotonic() - self._t0, 1)}), file=sys.__stdout__, flush=True)

    def addSuccess(self, test):
        super().addSuccess(test)
        self._emit(test, "pass")

    def addFailure(self, test, err):
        super().addFailure(test, err)
        self._emit(test, "fail", "".join(traceback.format_exception(*err)))

    def addError(self, test, err):
        super().addError(test, err)
        self._emit(test, "fail", "".join(traceback.format_exception(*err)))

    def addSkip(self, test, reason):
        super().addSkip(test, reason)
        self._emit(test, "skip", reason)


def flatten(suite):
    for item in suite:
        if isinstance(item, unittest.TestSuite):
            yield from flatten(item)
        else:
            yield item


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dir", required=True, help="the suite's interoperability/ directory")
    ap.add_argument("--file", required=True, choices=["client_test.py", "client_test5.py"])
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--exclude", default="", help="comma-separated tests not to run")
    ap.add_argument("tests", nargs="*")
    args = ap.parse_args()

    suite = os.path.abspath(args.dir)
    os.chdir(suite)
    sys.path.insert(0, suite)
    selected = [f"Test.{t}" for t in args.tests]

    def run_tests(*_a, **_k):
        module = sys.modules["__main__"]
        loader = unittest.TestLoader()
        tests = loader.loadTestsFromNames(selected, module) if selected else loader.loadTestsFromTestCase(module.Test)
        excluded = set(filter(None, args.exclude.split(",")))
        unittest.TestSuite(t for t in flatten(tests) if t._testMethodName not in excluded).run(JsonResult())

    unittest.main = run_tests
    # The suite's prints (and its clients' traces) go to stderr: stdout
    # carries only the JSON lines.
    sys.stdout = sys.stderr
    # No -h: client_test.py takes any option within "--help" (`o in ("--help")` is a
    # substring test) for --help; the suite connects to localhost.
    sys.argv = [args.file, "-p", str(args.port)]
    runpy.run_path(os.path.join(suite, args.file), run_name="__main__")


if __name__ == "__main__":
    main()
