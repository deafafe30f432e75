"""``companion eval``: the paper's studies (section V-A), in process or on real PX4 SITL.

* ``suites``: what each suite (table1, latency, vrel, baseline) runs and how it aggregates;
* ``pool``: a suite's runs on the in-process simulator, in a local process pool (``run_suite``);
* ``px4``: a suite's runs flown by the complete app against PX4 SITL (SIH), in real time;
* ``dispatch``: ``evaluate(..., autopilot="in-process" | "px4")``, the one entry whatever flies the runs;
* ``tune``: Bayesian tuning of k_pn and gamma_bar (paper IV-D) and its config overlay;
* ``cluster``: the in-process runs as Ray tasks (``--cluster``), ``px4ray``: PX4 instances as Ray actors;
* ``stats``: Wilson intervals of success rates, ``compare``: ``eval compare A B`` (differences beyond noise);
* ``tables``: Markdown tables and JSON encoding; ``plots``: the figures;
* ``cli``: the ``companion eval`` command.
"""
