"""Reading data: one trajectory representation, readers into it, data sets by name, derived views."""
