"""``wavegrasp gate``: the safety boundary between a grasp plan and the arm (paper section IV-H).

A plan goes only while the predictor's recent error stays within ``epsilon_m`` (the paper's
ē ≤ ε over a window Δt_w) and every other check passes: fresh inputs, time left to start,
upstream services alive, no abrupt change, no other plan executing. When in doubt: no-go.
"""
