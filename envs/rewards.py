"""The paper's reward functions: motion-planner r^m and decision-maker r^d (III-D)."""

from __future__ import annotations

import numpy as np

from gccp_envs.action import EgoState
from gccp_envs.config import IntersectionConfig
from gccp_envs.geometry import FloatArray, wrap_angle


def goal_errors(ego: EgoState, goal: FloatArray) -> tuple[float, float]:
    """Distance [m] and absolute heading difference [rad] between the ego and a goal pose."""
    distance = float(np.hypot(goal[0] - ego.x, goal[1] - ego.y))
    return distance, float(abs(wrap_angle(goal[2] - ego.heading)))


def goal_reached(config: IntersectionConfig, errors: tuple[float, float]) -> bool:
    """Whether a subgoal counts as reached (within the reach radius and heading tolerance)."""
    return errors[0] <= config.subgoal_reach_radius and errors[1] <= config.subgoal_reach_heading


def planner_reward(
    config: IntersectionConfig,
    before: tuple[float, float],
    after: tuple[float, float],
    arrived: bool,
    crashed: bool,
    offroad: bool,
    wrong_exit: bool = False,
) -> dict[str, float]:
    """Terms of r^m = r_time + r_arr + r_col + r_off + r_dist + r_head for one step.

    :param before: goal errors (distance, heading) before the step
    :param after: goal errors after the step
    :param arrived: whether the goal was reached in this step (paid once per goal)
    :param crashed: whether the ego collided
    :param offroad: whether the ego left the road
    :param wrong_exit: whether the ego left by another exit than its task's (paid as leaving the road
        when ``wrong_exit_penalty``)
    :return: the terms by name; their sum is the reward
    """
    return {
        "r_time": config.r_time,
        "r_arr": config.r_arr if arrived else 0.0,
        "r_col": config.r_col if crashed else 0.0,
        "r_off": config.r_off if offroad or (wrong_exit and config.wrong_exit_penalty) else 0.0,
        "r_dist": config.eps_d * (before[0] - after[0]),
        "r_head": config.eps_h * (before[1] - after[1]),
    }


def decider_reward(
    config: IntersectionConfig, task_reached: bool, subgoal_reached: bool, subgoal_distance: float
) -> dict[str, float]:
    """Terms of r^d = r_goal + r_subgoal + r_subgoal_dist for one decision.

    :param task_reached: whether the task goal was reached during the option
    :param subgoal_reached: whether the subgoal was reached within T_m steps
    :param subgoal_distance: distance [m] from the ego to the chosen subgoal when it was chosen
    :return: the terms by name; their sum is the reward
    """
    return {
        "r_goal": config.r_goal if task_reached else 0.0,
        "r_subgoal": config.r_subgoal if subgoal_reached else 0.0,
        "r_subgoal_dist": config.r_near + config.eps_s * subgoal_distance,
    }
