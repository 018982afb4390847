"""Previews: the nominal throw from the machine's joint state and the Monte Carlo scatter ellipse."""
