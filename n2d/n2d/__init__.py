"""n2d bringup: the n2d command-line tool, launch files and the end-to-end demo."""
