"""What is made from a trained run: its model loaded back with its settings checked (``trained``), frames
and videos along a camera path (``frames``), the camera path files they are read from and saved to
(``camera_files``), meshes and point clouds (``mesh``, ``ply``), and the live viewer (``viewer``)."""
