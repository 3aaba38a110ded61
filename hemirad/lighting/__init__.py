"""What the light does where people are: sensors, calculation grids and photometric units,
read from a solved mesh by final gathers."""
