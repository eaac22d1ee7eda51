"""user - layer 6, the user manager of thesis section 6.1.2: the API a task's code calls
(:class:`chcos.user.context.TaskContext`) and each task's world model.
"""
