"""Reading fragment files and writing outputs: one module per format family."""
