"""Building blocks of the live 3D viewer: the mine's and the planner's geometry for the browser."""
