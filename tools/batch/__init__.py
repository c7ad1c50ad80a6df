"""`slam batch`: many `slam run`s (sequences x configurations x repeats), gathered into one folder.

- ``spec.py`` the batch spec (YAML or command line) and the one function that builds its runs;
- ``task.py`` one run on a worker: `slam run` in its own process, then its evaluation;
- ``measure.py`` a run's numbers: accuracy against ground truth (APE/RPE through
  ``slam.evaluation``, se3 and posyaw), its stats summarised (also ``slam bench``'s columns);
- ``engines.py`` who executes the runs: ``local`` (a pool on this machine) or ``ray`` (a cluster);
- ``report.py`` run folders, resumption, tables; ``plots.py`` box plots and trajectories;
- ``runner.py`` ties them: build, skip finished runs, execute, write as runs finish.
"""
