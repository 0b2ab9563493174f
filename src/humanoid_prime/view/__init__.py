"""The live 3D view of Prime in a browser (served locally by viser, fully offline)."""
