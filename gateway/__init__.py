"""The zenoh side of bsc: samples -> estimator -> efforts; monitor -> alerts; recorder -> MCAP."""
__version__ = "0.1.0"

import drivers as _drivers  # noqa: E402,F401  (sets numba's cache directory first: drivers/jitcache.py)

# The arithmetic of the compiled kernels that turn frames into samples and efforts
# (drivers/kernel.py, gateway/estimator/core.py, chain_kernel.py, thruster_kernel.py). Bump it with
# any change that alters a bit of a published sample or effort: every recorded session carries it
# (metadata bsc.session "kernels"), and `bsc replay --check` says when a log's efforts came from
# other kernels. 2: the thruster fault detector (gateway/estimator/fdi.py) holds the filter's
# learning while it suspects a fault and models a confirmed one. 3: the joint filter
# (gateway/estimator/joint_filter.py): joint accelerations and each F/T sensor's bias from the
# F/T sensor and the encoder rates; full torques the distal and sensor sides fused per joint;
# JointEfforts.ft_bias; and the thruster filter's innovation gate and the clearing of a stuck
# valve (gateway/estimator/fdi.py). 4: contact detection (JointEfforts.contact); the sensor side
# without the learnt F/T bias; the fault detector's 0.2 s warm-up and the clearing of a partial
# loss; the thrusters' shared gain in the thruster filter's prior and the IMU weighed as measured
# above the healthy noise level; the learned per-valve wrenches (efforts/valves). 5: a confirmed
# leak modelled in the thruster filter's measurement and the published wrench, a fault measured
# below its smallest size dismissed (gateway/estimator/fdi.py); the thruster command's keep-out
# mask (ThrusterCommand.allowed, drivers). Healthy sessions: the same bits as 4. 6: a thruster's
# misalignment change (a tilt of its thrust) a hypothesis of the fault detector, named and put into
# the thruster filter (gateway/estimator/fdi.py). 7: a confirmed partial loss put into the thruster
# filter with room to refine its size only (rank one along the valve's nominal wrench), not its
# direction and moment arm; a misalignment its two angles only (gateway/estimator/fdi.py). Healthy
# sessions and those without a partial loss or a misalignment named: the same bits as 6. 8: the
# contact test learns the model's relative error from the arm's motion (floor 1 %) and leaves
# contact on a leaky count; no contact begins while the thruster fault detector suspects a fault
# (gateway/estimator/joint_filter.py, core.py). Sessions where no contact is flagged: the same bits
# as 7. 9: the thruster fault detector's loss CUSUMs follow what the filter learns of a loss
# before it is raised (gateway/estimator/fdi.py, follow), and a misalignment goes into the filter
# with the cosine of its angle (the thrust along the old direction shrinks); a session in which the
# detector never suspects a fault gives the same bits (the filter depends on the detector only
# through its suspicion and its alarms). 10: a valve whose loss CUSUM is above the detector's
# hold_valve (10) keeps its learned wrench while the rest of the thruster filter learns (a Schmidt
# "consider" update, gateway/estimator/thruster_kernel.py imu_tap, fdi.holding), so a loss being
# decided is not learnt into it; sessions where no loss CUSUM passes 10 give the same bits as 9.
# 11: a stuck valve raised by the short window with nothing measured since (a valve not commanded
# since) takes its size from the CUSUM of the same hypothesis when that is larger, and below the
# type's threshold waits for the valve's next command; a stuck valve raised by the long window is
# confirmed as the short window's are once it has data of its own (fdi.py); sessions without such
# alarms: the same bits as 10. 12: the short detector also runs a CUSUM per open and loss
# hypothesis tuned for a stuck valve (size 1), whose statistic and size count where larger than
# its window's and above 80 (fdi.GROSS_FLOOR); a fault the short detector raises starts its sums
# from that CUSUM's (fdi.py). Healthy sessions stay below 80 (peaks 24-45): the same bits as 11.
# 13: a partial loss or leak the long detector raises is sized on its CUSUM's sums before the
# alarm and its own since, pooled (fdi.py, _F_PA); its dismissal still tests its own size alone.
# Sessions without such an alarm: the same bits as 12. 14: the gross CUSUM is off (fdi.GROSS_FLOOR
# infinite): at 80 it raised 30 % leaks as other thrusters stuck open. The short detector is 11's.
# 15: the gross CUSUM back, for the short window's best hypothesis only and at a size of at least
# 0.8 (fdi._gross, GROSS_MIN_SIZE). Sessions where it never counts (healthy ones: peaks 24-45,
# under its floor of 80): the same bits as 14.
KERNELS = "15"
