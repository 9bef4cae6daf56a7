"""Physics of the emulated bench at the controller rate: pure functions over state arrays.

A package of stages, each a small numba function tested alone, inlined into one control-period loop:

| module        | stage                                                                   | owns      |
|---------------|-------------------------------------------------------------------------|-----------|
| firmware.py   | torque -> current references (MTPA / field weakening), PI current       | P_ S_ X_  |
|               | control, closed-loop field weakening, injection (eq. 2-4, 12), eq. 11   |           |
|               | voltage estimate, decoupling (section 3.1), torque estimate              |           |
| inverter.py   | 1.5-period delay / ZOH average, dead-time voltage                        | P_ X_     |
| machine.py    | dq PMSM (eq. 18-19, exact ZOH), saturation tables, torque (eq. 20) + d   | P_ X_     |
| mechanics.py  | shaft, load machine, accelerometer H = J G_Salpha (section 2.3)          | P_ S_ X_  |
| daq.py        | counts and the DAQ frame, laid out by drivers/daq_protocol.py            | P_ S_     |
| loop.py       | `simulate` (the stages in hardware order), summary/trace rows, `Plant`   | Y_ TR_    |

Everything is in SI units; no CAN, no pty, no threads here, so tests run the physics directly. The
state, parameters and setpoints are flat float64 arrays indexed by the X_*/P_*/S_* constants, each
declared by the stage that owns it; this package exports them all under one name, so callers write
`ph.P_TS`, `ph.S_TORQUE_NM`, `ph.simulate`, `ph.Plant`.
"""

from .daq import FRAME_BYTES, OVER_RANGE_FLAG, P_ALPHA_FS, S_SYNC, SYNC_FLAG
from .firmware import (
    MAX_INJECTION_ORDERS,
    P_FW_BW,
    P_FW_TARGET,
    P_IMAX,
    P_KI_D,
    P_KI_Q,
    P_KP_D,
    P_KP_Q,
    P_LD_NOM,
    P_LQ_NOM,
    P_PSI_NOM,
    P_R_NOM,
    P_TS,
    P_V_MARGIN,
    P_W_BW,
    S_DECOUPLING,
    S_H,
    S_POWER,
    S_THETA_COS,
    S_THETA_SIN,
    S_TORQUE_NM,
    S_UDC_V,
    S_VEST,
    S_XH_COS,
    S_XH_ORDER,
    S_XH_SIN,
    X_FW_DID,
    X_IF_D,
    X_IF_Q,
    X_IHAT_D,
    X_IHAT_Q,
    X_INT_D,
    X_INT_Q,
    X_VD_APP,
    X_VQ_APP,
    current_reference,
    mtpa_id,
    scheduled_theta,
)
from .inverter import P_ANGLE_COMP, P_F_PWM, P_I_ZC, P_T_DEAD, X_UD_APP, X_UQ_APP
from .loop import (
    N_PARAMS,
    N_SETPOINTS,
    N_STATE,
    N_SUMMARY,
    N_TRACE,
    NO_THETA_SCHEDULE,
    OMEGA_RECOMPUTE_RAD_S,
    TR_ALPHA,
    TR_ALPHA_MEAS,
    TR_DIST,
    TR_ID,
    TR_IQ,
    TR_OMEGA_M,
    TR_PHI_E,
    TR_T_LOAD,
    TR_TORQUE,
    TR_UD,
    TR_UD_DT,
    TR_UD_STAR,
    TR_UQ,
    TR_UQ_DT,
    TR_UQ_STAR,
    TR_V_INJ,
    X_SAMPLES,
    Y_ID_REF,
    Y_IQ_REF,
    Y_LOAD_TORQUE_SUM,
    Y_OMEGA_SUM,
    Y_OVER_RANGE,
    Y_TORQUE_EST_SUM,
    Y_UD_SUM,
    Y_UQ_SUM,
    Plant,
    new_setpoints,
    new_state,
    simulate,
    steady_state_init,
)
from .machine import (
    MAX_FURTHER_HARMONICS,
    P_DIST_SCALE,
    P_DMAP_NN,
    P_DMAP_NT,
    P_DMAP_OFF,
    P_H_DIST,
    P_LD,
    P_LQ,
    P_NP,
    P_OFF_DECAY,
    P_PSI,
    P_R,
    P_SAT_DECAY,
    P_SAT_N,
    P_SAT_OFF,
    P_T_RATED,
    P_XH_N,
    P_XH_OFF,
    X_ID,
    X_IMAG_F,
    X_IQ,
    disturbance_phasor,
    map_phasor,
    saturated_params,
    zoh_dq,
)
from .mechanics import (
    P_B,
    P_H_A1,
    P_H_A2,
    P_H_B0,
    P_H_B1,
    P_H_B2,
    P_J,
    P_LOAD_KI,
    P_LOAD_KP,
    P_LOAD_RAMP,
    P_LOAD_TMAX,
    P_NOISE,
    S_LOAD_ACCEL,
    S_LOAD_DECEL,
    S_LOAD_ON,
    S_LOAD_SPEED,
    X_H_S1,
    X_H_S2,
    X_LOAD_INT,
    X_LOAD_REF,
    X_OMEGA_M,
    X_PHI_E,
    sensor_biquad,
    sensor_response,
)
