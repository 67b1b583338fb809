"""The simulator: terrain, vehicle, camera and laser, written as a dataset folder with its ground
truth (:func:`dem_graph.sim.pipeline.simulate`; the scenarios: :mod:`dem_graph.sim.scenarios`)."""
