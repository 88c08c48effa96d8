"""Image effects a scene may declare (numpy only). Each runs only when the layer asks for it."""
