"""`splatk bench`: methods (:mod:`.methods`), the runner (:mod:`.runner`), the stability matrix
(:mod:`.stability`) and the charts (:mod:`.charts`)."""
from .methods import METHOD_KEYS, expand_grid, fit_config_for, load_bench_file, method_id
from .runner import RESULT_KEYS, BenchConfig, BenchResult, BenchStopped, load_results, run_bench, run_one, table_rows
from .stability import (COLLAPSE_DB, STABILITY_CONDITIONS, STABILITY_KERNELS, classify, run_stability,
                        stability_methods)

__all__ = ["METHOD_KEYS", "expand_grid", "fit_config_for", "load_bench_file", "method_id", "RESULT_KEYS",
           "BenchConfig", "BenchResult", "BenchStopped", "load_results", "run_bench", "run_one", "table_rows",
           "COLLAPSE_DB", "STABILITY_CONDITIONS", "STABILITY_KERNELS", "classify", "run_stability", "stability_methods"]
