"""The link to the board: what the driver has proved about the firmware's parser, and how it proves it."""
