"""The Viser authoring app (issue: web). Not implemented yet."""
