"""Length units that files and streams may use; ivc itself works in metres."""

#: metres per unit
LENGTH_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
