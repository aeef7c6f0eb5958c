"""Python scenario driver: python main.py --lib pika|aio-pika|kombu|raw|streams|semantics --url URL [--list]"""

import importlib
import sys

import harness

MODULES = {"pika": "s_pika", "aio-pika": "s_aiopika", "kombu": "s_kombu", "raw": "s_raw", "streams": "s_streams", "semantics": "s_semantics"}

if __name__ == "__main__":
    lib = None
    if "--lib" in sys.argv:
        i = sys.argv.index("--lib")
        lib = sys.argv[i + 1]
        del sys.argv[i : i + 2]
    libs = [lib] if lib else list(MODULES)
    for name in libs:
        importlib.import_module(MODULES[name])
    sys.exit(harness.main(libs))
