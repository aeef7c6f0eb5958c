"""Upstream client test suites, fetched from package registries at run time
into the cache directory (never committed), pointed at the broker under test.

Each runner takes a Ctx and returns [(test_id, status, detail)] with status
"pass", "fail" or "skip".
"""


class SetupError(Exception):
    pass


class Ctx:
    def __init__(self, **kw):
        self.__dict__.update(kw)


SUITES = {}
