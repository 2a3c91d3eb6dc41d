"""skidbench.pipeline.simulate"""
