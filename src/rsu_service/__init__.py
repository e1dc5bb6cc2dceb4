"""The roadside unit: perception sources, the RSU pipeline (track, predict, publish) and its node."""
