"""Vision-language region analysis, weight maps and semantic uncertainty."""
