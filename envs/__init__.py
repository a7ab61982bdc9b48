"""The intersection world of sb3_gccp (installed as ``gccp_envs``)."""
