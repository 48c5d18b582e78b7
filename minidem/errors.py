"""The one exception base users catch: every error minidem raises on purpose derives
from :class:`MinidemError`.

* ``minidem.ScenarioError`` (bad input: a scenario key, a file, an option; the CLI exits 2),
* ``minidem.LawError`` (an unknown or broken contact law; exit 2),
* ``minidem.RunFailure`` (the run started and could not finish: a blow-up; exit 1),
* ``minidem.OutputError`` (a result file could not be written: disk full, permissions; exit 1;
  an OSError too).

It lives in a module of its own, below every stage, so that each stage can derive its
error from it without importing another stage.
"""


class MinidemError(Exception):
    """Base of every error minidem raises on purpose (bad input, a broken law, a failed run)."""


class ScenarioError(MinidemError):
    """Bad input: the CLI prints the message and exits with code 2. Raised by the scenario
    reader (``minidem.scene.scenario``, which every caller imports it from) and by the
    checks of what its values imply (``minidem.scene.derived``), which lies below it."""
