"""Launch description, parameters, episode runner and the area3d command."""
