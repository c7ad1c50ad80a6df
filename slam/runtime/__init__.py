"""The runtime: stages, worker processes, the reader, the player, the viewer, the wiring of a
run and its end. Estimators (``slam.frontend``, ``slam.backend``, ``slam.loop``, ``mapping``)
never import it."""
