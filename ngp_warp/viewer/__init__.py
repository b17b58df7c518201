"""The web viewer (viser) of a trained run or of a scene trained live (``server``)."""
