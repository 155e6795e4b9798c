"""LeafSystems of the station and the application, one concern per module."""
