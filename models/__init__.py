"""Dynamics models: the nominal quadrotor (numpy, CasADi, torch renderings) and KNODE residuals."""
