"""ICP-based position-based visual servoing (issues: servo core, simulation). Not implemented yet."""
