"""cfknode: KNODE-MPC-Online flight stack for Crazyflie 2.x."""

__version__ = "0.1.0"
