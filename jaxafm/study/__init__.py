"""Monte-Carlo positioning studies: the trials of many drawn scanners in sharded batches
(``monte_carlo``) over every device of every JAX process (``processes``), and their summaries.

Imports positioning and everything below it; importing it switches JAX to float64
(``jaxafm._precision``).
"""

from .. import _precision  # noqa: F401  (float64 before any array of this package exists)
