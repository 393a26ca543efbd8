"""The space robot as hardware: dynamics, friction, thrusters, controller, sensors and their CAN firmware."""
