"""A physics-based wave tank that makes Trisect-like recordings (``wavegrasp record``).

``waves``: linear (Airy) wave kinematics in finite depth, regular and JONSWAP seas, slow sway.
``body``: a buoyant object on a taut tether in that flow (Morison forces, added mass).
``camera``: a Trisect-like stereo camera (ray casting, depth noise, dropouts, marine snow).
``record``: the command that ties them together and writes the MCAP recording.
"""
