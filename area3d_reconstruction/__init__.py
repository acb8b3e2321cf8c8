"""AREA3D's live reconstruction: the frames the planner fuses integrated into a TSDF volume (the
evaluation's `area3d_eval.reconstruct.TsdfFusion`), its coloured mesh published, the volume saved,
loaded and its mesh exported."""
